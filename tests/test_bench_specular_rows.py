import re

import pytest
import torch

from rtsplat.bench import specular_rows


def test_the_row_count_bench_prints_every_precision_and_kind(capsys):
    threads = torch.get_num_threads()
    assert specular_rows.main(["--rows", "300", "--spread", "50", "--steps", "2", "--rounds", "1",
                               "--width", "16"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: [float(v) for v in line.split()[1:]] for line in lines
            if re.match(r"^(float32|bfloat16)\s", line)}
    assert set(rows) == {"float32", "bfloat16"}
    assert all(len(values) == 3 and all(v > 0 for v in values) for values in rows.values())
    passes = {line.split()[0]: float(line.split()[1]) for line in lines if re.match(r"^(reference|kernels)\s", line)}
    assert set(passes) == {"reference", "kernels"} and all(v > 0 for v in passes.values())
    ratio = [line for line in lines if line.startswith("median of the per-round ratios")]
    assert len(ratio) == 1 and float(ratio[0].split()[-1]) > 0
    assert torch.get_num_threads() == threads  # timed on one thread, the caller's count restored


def test_the_row_count_bench_refuses_a_spread_as_large_as_the_rows():
    with pytest.raises(SystemExit):
        specular_rows.main(["--rows", "100", "--spread", "100"])
