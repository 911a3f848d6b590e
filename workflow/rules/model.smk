# Training, rendering, metrics and the report. The CLIs belong to the model and report stages;
# until those exist they print "not implemented yet" and exit with status 3.


rule train:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
    output:
        directory(f"{RESULTS}/{{scene}}/runs/{{method}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/train_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/train_{{method}}.tsv"
    params:
        cfg=stage_json("train"),
    threads: 4
    resources:
        gpu=1,
        runtime=720,
        mem_mb=32000,
    conda:
        ENV
    shell:
        "{RTSPLAT} train --scene {input.prepared} --method {wildcards.method} --out {output} "
        "--config-json {params.cfg} > {log} 2>&1"


rule render:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        run=f"{RESULTS}/{{scene}}/runs/{{method}}",
    output:
        directory(f"{RESULTS}/{{scene}}/renders/{{method}}"),
    log:
        f"{RESULTS}/{{scene}}/logs/render_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/render_{{method}}.tsv"
    params:
        cfg=stage_json("render"),
    resources:
        gpu=1,
        runtime=120,
        mem_mb=16000,
    conda:
        ENV
    shell:
        "{RTSPLAT} render --scene {input.prepared} --run {input.run} --out {output} "
        "--config-json {params.cfg} > {log} 2>&1"


rule metrics:
    input:
        prepared=f"{RESULTS}/{{scene}}/prepared",
        renders=f"{RESULTS}/{{scene}}/renders/{{method}}",
    output:
        f"{RESULTS}/{{scene}}/metrics/{{method}}.json",
    log:
        f"{RESULTS}/{{scene}}/logs/metrics_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scene}}/benchmarks/metrics_{{method}}.tsv"
    params:
        cfg=stage_json("metrics"),
    conda:
        ENV
    shell:
        "{RTSPLAT} metrics --scene {input.prepared} --renders {input.renders} --out {output} "
        "--config-json {params.cfg} > {log} 2>&1"


rule report:
    input:
        expand(f"{RESULTS}/{{scene}}/metrics/{{method}}.json", scene=SCENES, method=METHODS),
    output:
        f"{RESULTS}/report/index.html",
    log:
        f"{RESULTS}/logs/report.log",
    benchmark:
        f"{RESULTS}/benchmarks/report.tsv"
    conda:
        ENV
    shell:
        "{RTSPLAT} report --results {RESULTS} --out {output} {input} > {log} 2>&1"
