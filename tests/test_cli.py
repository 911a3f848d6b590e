import subprocess
import sys

import pytest

from rtsplat import cli


def test_help_lists_every_stage(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for stage in cli.STAGES:
        assert stage.name in text


def test_unimplemented_stage_says_so_and_exits_nonzero(monkeypatch, capsys):
    fake = cli.Stage("future", "rtsplat.no_such_stage_module", "a stage that does not exist yet")
    monkeypatch.setattr(cli, "STAGES", (*cli.STAGES, fake))
    assert cli.main(["future"]) == cli.NOT_IMPLEMENTED_EXIT
    assert "not implemented yet" in capsys.readouterr().err


def test_bad_input_of_any_stage_is_printed_once_and_exits_1(monkeypatch, tmp_path, capsys):
    (tmp_path / "failing_stage_mod.py").write_text(
        "from rtsplat.errors import ConfigError\n"
        "def add_arguments(parser):\n    parser.add_argument('--n', type=int, required=True)\n"
        "def run(args):\n    raise ConfigError('n is bad', path='x.yaml', fix='use another n')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cli, "STAGES", (*cli.STAGES, cli.Stage("failing", "failing_stage_mod", "always fails")))
    assert cli.main(["failing", "--n", "1"]) == cli.BAD_INPUT_EXIT == 1
    assert capsys.readouterr().err == "rtsplat failing: error: x.yaml: n is bad\n  Fix: use another n\n"
    with pytest.raises(SystemExit) as exc:  # a usage error stays argparse's status 2
        cli.main(["failing"])
    assert exc.value.code == 2


def test_a_missing_dependency_inside_a_stage_is_not_reported_as_unimplemented(monkeypatch, tmp_path):
    (tmp_path / "broken_stage_mod.py").write_text("import a_dependency_that_is_not_installed\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    stage = cli.Stage("broken", "broken_stage_mod", "imports a missing package")
    with pytest.raises(ModuleNotFoundError, match="a_dependency_that_is_not_installed"):
        cli._load(stage)


def test_demo_cli_writes_real_images(tmp_path):
    import cv2

    out = tmp_path / "demo"
    result = subprocess.run(
        [sys.executable, "-m", "rtsplat.cli", "demo", "--out", str(out), "--width", "96", "--height", "72"],
        capture_output=True, text=True, check=False,
    )
    assert result.returncode == 0, result.stderr
    color = cv2.imread(str(out / "volume_color.png"))
    alpha = cv2.imread(str(out / "surface_alpha.png"))
    volume_alpha = cv2.imread(str(out / "volume_alpha.png"))
    assert color.shape == (72, 96, 3)
    assert color.std() > 10  # a textured render, not a flat image
    # the glass pane is in the surface G-buffer but lets the volume color through
    assert (alpha.astype(int) - volume_alpha.astype(int)).max() > 100


# run by the benchmark workers under other checkouts (rtsplat.bench.workers), whose rtsplat may lack run_command
WORKER_SCRIPTS = {"raster_cpu.py"}


def test_every_python_m_command_prints_the_error_type_as_one_line(tmp_path):
    """Every module a user runs with ``python -m`` turns the project's error type into one line and status 1
    (rtsplat.errors.run_command), as ``rtsplat <stage>`` does: shown on one of them, required of all."""
    from pathlib import Path

    package = Path(cli.__file__).parent
    scripts = [p for p in package.rglob("*.py") if 'if __name__ == "__main__"' in p.read_text()]
    assert len(scripts) > 10
    unhandled = [str(p.relative_to(package)) for p in scripts
                 if "run_command(" not in p.read_text() and p.name not in WORKER_SCRIPTS and p.name != "cli.py"]
    assert not unhandled, f"python -m commands whose errors would show as a traceback: {unhandled}"
    result = subprocess.run([sys.executable, "-m", "rtsplat.bench.layer_ceiling", "--data", str(tmp_path),
                             "--renders", str(tmp_path)], capture_output=True, text=True, check=False)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith(f"python -m rtsplat.bench.layer_ceiling: error: {tmp_path / 'gt_layers'}")
