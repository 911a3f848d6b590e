"""Tests of the scene family (rtsplat.synth.family): names, parameters, geometry and tiny renders of every kind."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
cv2 = pytest.importorskip("cv2")

from rtsplat.cli import main as cli_main  # noqa: E402
from rtsplat.errors import ConfigError  # noqa: E402
from rtsplat.synth.dataset import SynthConfig  # noqa: E402
from rtsplat.synth.family import (  # noqa: E402
    CAPTURES,
    GLASS,
    KINDS,
    Member,
    build_member,
    draw_params,
    held_out_members,
    members,
    parse_name,
)
from rtsplat.synth.render import load_scene, set_variant  # noqa: E402

TINY = ["--views", "6", "--width", "64", "--height", "48", "--spp", "4", "--layer-spp", "4", "--any-views"]
# the share of each view that the glass covers, per kind (median over the views of a tiny render)
COVERAGE = {"shop_window": (0.6, 0.95), "curved": (0.1, 0.8), "case": (0.1, 0.8), "car": (0.1, 0.8),
            "grazing": (0.2, 0.9)}


# one member of each kind, orbits and walks, tuning and seen seeds, every glass, both curved sections
TINY_SEEDS = {"shop_window": 1, "curved": 2, "case": 3, "car": 0, "grazing": 3}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """A member of every kind (TINY_SEEDS) rendered tiny through the CLI."""
    root = tmp_path_factory.mktemp("family")
    outs = {}
    for kind, seed in TINY_SEEDS.items():
        out = root / kind
        assert cli_main(["synth", "--scene", f"family/{kind}-{seed}", "--out", str(out), "--no-progress", *TINY]) == 0
        outs[kind] = out
    return outs


def _masks(out: Path) -> list[np.ndarray]:
    return [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) > 127 for p in sorted((out / "transparent_masks").glob("*.png"))]


def test_names_seeds_and_splits():
    m = parse_name("family/shop_window-3")
    assert (m.kind, m.seed, m.split, m.name, m.dataset_name) == (
        "shop_window", 3, "seen", "family/shop_window-3", "shop_window-3")
    assert [parse_name(f"family/car-{seed}").split for seed in (0, 1, 2, 3, 5, 10, 99, 100, 103, 104)] == [
        "tuning", "seen", "tuning", "seen", "tuning", "tuning", "tuning", "held_out", "held_out", "tuning"]
    for bad in ("family/boat-1", "family/car", "family/car-x", "family/car--1", "family/"):
        with pytest.raises(ValueError) as info:
            parse_name(bad)
        assert all(kind in str(info.value) for kind in KINDS), info.value
    with pytest.raises(ConfigError, match="shop_window"):
        SynthConfig(scene="family/boat-1").validate()
    with pytest.raises(ConfigError, match="family/<kind>-<seed>"):
        SynthConfig(scene="domes").validate()
    SynthConfig(scene="family/grazing-7").validate()


def test_cli_rejects_a_bad_family_name(tmp_path, capsys):
    rc = cli_main(["synth", "--scene", "family/boat-1", "--out", str(tmp_path / "x"), "--no-progress", *TINY])
    assert rc != 0
    err = capsys.readouterr().err
    assert "boat" in err and all(kind in err for kind in KINDS), err
    assert not (tmp_path / "x").exists()


def test_parameters_come_from_the_seed():
    for kind in KINDS:
        params = [draw_params(Member(kind, s)) for s in range(6)]
        assert params == [draw_params(Member(kind, s)) for s in range(6)]  # same seed, same parameters
        texts = [json.dumps(p, sort_keys=True) for p in params]
        assert len(set(texts)) == len(texts), kind  # different seeds, different parameters
    family = members(seeds=range(4))
    assert len(family) == 4 * len(KINDS) >= 16
    for kind in KINDS:
        for split in ("tuning", "seen"):
            mine = [m for m in family if m.kind == kind and m.split == split]
            assert {m.capture for m in mine} == set(CAPTURES), (kind, split)
        held = [m for m in held_out_members() if m.kind == kind]
        assert {m.capture for m in held} == set(CAPTURES) and {m.glass for m in held} == set(GLASS), kind
    assert {m.glass for m in family} == set(GLASS)
    tints = {m.glass: draw_params(m)["tint"] for m in family if m.kind == "case"}
    assert tints["clear"] == (1.0, 1.0, 1.0)
    assert max(tints["dim"]) <= 0.45 and len(set(tints["tinted"])) > 1  # grey and dim; coloured


def _obj(path: Path, tag: str) -> np.ndarray:
    return np.array([[float(x) for x in line.split()[1:4]] for line in path.read_text().splitlines()
                     if line.startswith(tag + " ")])


@pytest.mark.parametrize("seed", [0, 1])  # 0: a cylindrical section, 1: a spherical cap
def test_curved_glass_is_curved(tmp_path, seed):
    set_variant()
    spec = build_member(f"family/curved-{seed}", tmp_path)
    section = spec.family["params"]["section"]
    assert section == ("cylinder", "sphere")[seed]
    glass = spec.elements["glass"]
    assert glass["face_normals"] is False  # shaded with the exact surface's normals
    points, normals = _obj(Path(glass["filename"]), "v"), _obj(Path(glass["filename"]), "vn")
    centred = points - points.mean(0)
    flatness = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(points))  # rms off the best plane
    assert flatness > 0.01, f"{section}: the glass is nearly flat ({flatness:.4f} m off its plane)"
    radius = spec.family["params"]["radius"]
    # every vertex lies at the glass's radius from one centre, and its normal points away from it
    centre = points - radius * normals
    assert np.allclose(centre, centre.mean(0), atol=1e-4) if section == "sphere" else \
        np.allclose(centre[:, 1:], centre[:, 1:].mean(0), atol=1e-4)
    spread = np.degrees(np.arccos(np.clip(normals @ normals.mean(0) / np.linalg.norm(normals.mean(0)), -1, 1)))
    assert spread.max() > 10.0


@pytest.mark.parametrize("name", ["family/curved-0", "family/curved-1", "family/car-2"])
def test_interior_is_seen_only_through_the_glass(tmp_path, name):
    """No pixel ray of the capture reaches an interior object without crossing the glass first, and some
    reach one through it."""
    from synth_rays import interior_hits

    set_variant()
    spec = build_member(name, tmp_path)
    cams = spec.orbit.cameras(8, 40, 30)
    bare, through = interior_hits(load_scene(spec.elements, cams, spp=1), cams)
    assert bare == 0, f"{name}: an interior object is visible without glass"
    assert through > 20, name


def test_tiny_renders_have_masks_layers_and_family_records(tiny):
    captures = set()
    for kind, out in tiny.items():
        seed = TINY_SEEDS[kind]
        description = json.loads((out / "scene.json").read_text())
        assert description["scene"] == f"family/{kind}-{seed}"
        family = description["family"]
        assert (family["kind"], family["seed"], family["split"]) == (kind, seed, ("tuning", "seen")[seed % 2])
        assert family["params"] == json.loads(json.dumps(draw_params(Member(kind, seed))))
        captures.add(description["camera_path"]["type"])
        assert description["camera_path"]["type"] == family["params"]["capture"]
        masks = _masks(out)
        assert len(masks) == 6 and all(m.any() for m in masks), kind
        coverage = [float(m.mean()) for m in masks]
        lo, hi = COVERAGE[kind]
        print(kind, "glass coverage per view:", " ".join(f"{c:.2f}" for c in coverage))
        assert lo <= float(np.median(coverage)) <= hi, (kind, coverage)
        for stem in ("0000", "0003"):
            with np.load(out / "layers" / "linear" / f"{stem}.npz") as layers:
                full, refl, trans = (layers[k].astype(np.float64) for k in ("full", "reflection", "transmission"))
            assert all(np.isfinite(x).all() for x in (full, refl, trans)), kind
            mask = masks[int(stem)]
            assert refl[mask].mean() > 1e-3 and trans[mask].mean() > 1e-3, kind  # the glass reflects and shows through
            assert refl[~_grow(mask)].max() == 0.0, kind  # no reflection off the glass
        check = description["layer_check"]
        assert abs(check["relative_residual"]) < 0.05, (kind, check)  # R + T adds up to the full render
        assert description["reflection_reach"]["glass_pixels"] > 0
    assert captures == {"orbit", "walk"}


def _grow(mask: np.ndarray) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def test_walk_path_views_look_from_the_segment_at_the_looked_at_points():
    from rtsplat.synth.cameras import WalkPath, camera_to_world_np

    path = WalkPath(start=(-1.0, -3.0, 1.2), end=(1.0, -3.0, 1.2), look_start=(-0.5, 0.0, 1.0),
                    look_end=(0.5, 0.0, 1.0), height_amplitude=0.1)
    eyes, targets = path.eyes(5), path.targets(5)
    assert np.allclose(eyes[[0, -1], :2], [[-1.0, -3.0], [1.0, -3.0]]) and np.ptp(eyes[:, 2]) > 0.05
    for cam, eye, target in zip(path.cameras(5, 40, 30), eyes, targets, strict=True):
        c2w = camera_to_world_np(cam)
        axis = (target - eye) / np.linalg.norm(target - eye)
        assert np.allclose(c2w[:3, 3], eye) and np.allclose(c2w[:3, 2], axis, atol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_grazing_views_meet_the_pane_at_grazing_angles(tmp_path, seed):
    """Every camera's optical axis meets the pane's plane (y = 0) at 10-36 degrees (0 would be in the plane)."""
    from rtsplat.synth.cameras import camera_to_world_np

    set_variant()
    spec = build_member(f"family/grazing-{seed}", tmp_path)
    for cam in spec.orbit.cameras(12, 40, 30):
        axis = camera_to_world_np(cam)[:3, 2]
        angle = np.degrees(np.arcsin(abs(axis[1])))
        assert 10.0 <= angle <= 36.0, (seed, angle)


@pytest.mark.parametrize("seed", range(4))
def test_shop_window_pane_fills_most_of_each_view(tmp_path, seed):
    """Ray-cast masks of 6 views at 40 x 30: the pane covers 60-95% of each."""
    from rtsplat.synth.render import first_hit_mask

    set_variant()
    spec = build_member(f"family/shop_window-{seed}", tmp_path)
    cams = spec.orbit.cameras(6, 40, 30)
    scene = load_scene(spec.elements, cams, spp=1)
    coverage = [float(first_hit_mask(scene, cam).mean()) for cam in cams]
    print(f"shop_window-{seed} ({spec.family['params']['capture']}) pane coverage:",
          " ".join(f"{c:.2f}" for c in coverage))
    assert all(0.6 <= c <= 0.95 for c in coverage), coverage


def test_the_held_out_list_is_fixed_in_benchmarks_and_says_it_decides_nothing():
    """benchmarks/heldout.yaml runs exactly the held-out members, each a scene of its own (parameters unlike
    every tuning and seen seed's), with the family benchmark's settings, under a header that forbids tuning on it."""
    import yaml

    from rtsplat.config import load_config

    root = Path(__file__).resolve().parent.parent
    text = (root / "benchmarks" / "heldout.yaml").read_text()
    config = yaml.safe_load(text)
    held = held_out_members()
    assert config["scenes"] == [m.dataset_name for m in held] and len(held) == 4 * len(KINDS)
    assert {m.split for m in held} == {"held_out"}
    assert not {m.dataset_name for m in held} & set(yaml.safe_load((root / "benchmarks" / "family.yaml").read_text())
                                                      ["scenes"])
    family = yaml.safe_load((root / "benchmarks" / "family.yaml").read_text())
    assert {k: v for k, v in config.items() if k != "scenes"} == {k: v for k, v in family.items() if k != "scenes"}
    assert load_config(root / "benchmarks" / "heldout.yaml").scenes == config["scenes"]  # a valid config of its own
    header = " ".join(line.lstrip("# ") for line in text.splitlines() if line.startswith("#"))
    assert "only when an issue's work is done" in header
    assert "never choose a default, a threshold or a rule from it" in header
    seen = {json.dumps(draw_params(m), sort_keys=True) for m in members(seeds=range(4))}
    assert not {json.dumps(draw_params(m), sort_keys=True) for m in held} & seen


def test_the_family_page_holds_both_halves_at_the_family_settings():
    """benchmarks/family_page.yaml (`make family-page`): one tuning and one held-out member of every kind, never a
    seen one, with the family benchmark's methods (a seed repeat of each) and settings, a valid config of its own."""
    import yaml

    from rtsplat.config import load_config

    root = Path(__file__).resolve().parent.parent
    config = yaml.safe_load((root / "benchmarks" / "family_page.yaml").read_text())
    family = yaml.safe_load((root / "benchmarks" / "family.yaml").read_text())
    chosen = [parse_name(scene) for scene in config["scenes"]]
    for split in ("tuning", "held_out"):
        assert sorted(m.kind for m in chosen if m.split == split) == sorted(KINDS), split
    assert len(chosen) == 2 * len(KINDS) and {m.dataset_name for m in chosen} <= (
        {m.dataset_name for m in held_out_members()} | set(family["scenes"]))
    assert {k: v for k, v in config.items() if k != "scenes"} == {k: v for k, v in family.items() if k != "scenes"}
    assert {"rtsplat_seed1", "2dgs_seed1"} <= set(config["methods"])
    assert load_config(root / "benchmarks" / "family_page.yaml").scenes == config["scenes"]


@pytest.mark.parametrize("kind", KINDS)
def test_every_held_out_member_builds_a_scene_whose_cameras_see_its_glass(tmp_path, kind):
    """The held-out seeds build (geometry, textures, cameras; nothing rendered) and, over pixel rays of four of
    their cameras at 32x24, the glass covers each view in the share the kind's tiny renders show."""
    from rtsplat.synth.render import first_hit_mask

    set_variant()
    lo, hi = COVERAGE[kind]
    for member in held_out_members():
        if member.kind != kind:
            continue
        workdir = tmp_path / member.dataset_name
        workdir.mkdir()
        spec = build_member(member.name, workdir)
        assert spec.family["split"] == "held_out" and spec.transparent
        cams = spec.orbit.cameras(4, 32, 24)  # the member's camera path, an orbit or a walk
        scene = load_scene(spec.elements, cams, spp=1)
        shares = [float(first_hit_mask(scene, cam).mean()) for cam in cams]
        assert lo <= float(np.median(shares)) <= hi and min(shares) > 0, (member.name, shares)
