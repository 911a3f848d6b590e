# rtsplat workflow: <data>/<scene>/images -> masks, sfm, prepared scene, trained models, renders,
# metrics and one report. Every rule only calls an `rtsplat <stage>` CLI; the logic is in rtsplat/.
#
#   snakemake --cores all                          # everything, locally
#   snakemake --cores all prepared_all             # up to the prepared scenes
#   snakemake --profile profiles/slurm             # on a SLURM cluster (train/render get a GPU)
#   snakemake --cores all --config data=/path/to/scenes
from snakemake.utils import min_version, validate

min_version("8.0")


configfile: "config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/preprocess.smk"
include: "workflow/rules/model.smk"


localrules:
    all,
    prepared_all,


rule all:
    default_target: True
    input:
        f"{RESULTS}/report/index.html",
