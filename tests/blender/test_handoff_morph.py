"""A hand-off rig smaller than the vertex animation it replaces.

Morph-target animations as engines ship them (one morph target per frame played by its weights:
three.js' Horse, Flamingo, Parrot) are made here with Blender (``morph_assets``): a posed rig's
cycle written without normals (a viewer shades it flat, as the Horse), and a flexing tube with UV
seams, hard edges, vertex colours and a material whose cross-sections also squash (no bone
explains that part). ``python -m artdef_addon fit X.glb --links auto --glb out.glb`` with the
default settings must write one mesh with one skin, no more vertices than the source's mesh, no
bigger than the source file, replaying the source at its keyed frames within 1.5 % (worst vertex)
and 0.3 % (RMS) of the bounding-box diagonal once read back; ``--residuals 0`` writes no morph
target.
"""

import json
import os

import numpy as np
import pytest

from conftest import REPO_ROOT

bpy = pytest.importorskip("bpy")

import morph_assets  # noqa: E402
from morph_assets import replay_error  # noqa: E402
from handoffhelpers import _ok, _run  # noqa: E402
from test_headless_gltf import _validate, read_glb  # noqa: E402

MAX_BAR = 0.015                 # of the bounding-box diagonal, the worst vertex of any keyed frame
RMS_BAR = 0.003


def _fit(source, out, *extra):
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(source), "--links", "auto", "--glb", str(out), *extra],
                    cwd=os.path.dirname(out)))
    return proc.stdout


def gltf_contents(path):
    gltf, _ = read_glb(path)
    prims = [p for m in gltf["meshes"] for p in m["primitives"]]
    return dict(meshes=len(gltf["meshes"]), skins=len(gltf.get("skins", [])),
                vertices=sum(gltf["accessors"][p["attributes"]["POSITION"]]["count"] for p in prims),
                targets=max(len(p.get("targets", [])) for p in prims),
                attributes=set().union(*(p["attributes"] for p in prims)),
                materials=len(gltf.get("materials", [])))


@pytest.fixture(scope="module")
def assets(installed_addon, tmp_path_factory):
    """The two morph files, written once: {name: (path, keyed frames)}."""
    d = tmp_path_factory.mktemp("morph")
    claw = np.load(REPO_ROOT / "tests" / "data" / "generated_claw.npz")
    # a fresh seed each module: the bars hold for a cycle of any phases and axes
    seed = int.from_bytes(os.urandom(2), "little")
    poses = morph_assets.rig_cycle(claw["vertices"], claw["gt_joints"], claw["gt_parents"], claw["gt_weights"],
                                   n_frames=24, seed=seed)
    out = {}
    _, frames = morph_assets.write_morph_glb(d / "claw.glb", claw["vertices"], claw["faces"], poses,
                                             name="Claw", normals=False)
    out["claw"] = (d / "claw.glb", frames)
    _, frames = morph_assets.write_morph_glb(d / "tube.glb", *morph_assets.wave_tube(seed=seed), name="Tube")
    out["tube"] = (d / "tube.glb", frames)
    print(f"seed {seed}")
    return out


@pytest.mark.parametrize("name", ["claw", "tube"])
def test_default_fit_is_a_smaller_rig_that_replays_the_source(assets, name, tmp_path):
    source, frames = assets[name]
    out = tmp_path / "rig.glb"
    log = _fit(source, out)
    src, rig = gltf_contents(source), gltf_contents(out)
    assert rig["meshes"] == 1 and rig["skins"] == 1
    assert rig["vertices"] <= src["vertices"], (rig, src)
    assert os.path.getsize(out) <= os.path.getsize(source), (os.path.getsize(out), os.path.getsize(source))
    # the source's colours, UVs and material come along; normals only where the source had them
    assert {"COLOR_0", "TEXCOORD_0"} <= rig["attributes"] and rig["materials"] == src["materials"] == 1
    assert ("NORMAL" in rig["attributes"]) == ("NORMAL" in src["attributes"])
    worst, rms = replay_error(source, out, frames)
    print(f"{name}: {rig['targets']} morph targets, {os.path.getsize(out):,} of {os.path.getsize(source):,} bytes, "
          f"replay max {100 * worst:.3f}% rms {100 * rms:.3f}%")
    assert worst < MAX_BAR and rms < RMS_BAR
    # the export says what it wrote and what it replaces
    line = next(ln for ln in log.splitlines() if ln.startswith(f"wrote {out}"))
    assert f"{rig['targets']} morph targets" in line and f"the source {source.name}" in line
    assert "residual shapes:" in log and "replay error skin alone" in log


def test_residual_shapes_correct_what_few_bones_leave(assets, tmp_path):
    """Four links cannot follow the flexing tube: the residual shapes chosen from the data bring
    the replay within the bars; ``--residuals 0`` is the skin alone (no morph target), and an
    asked count is kept."""
    source, frames = assets["tube"]
    runs = {}
    for setting in ("auto", "0", "2"):
        out = tmp_path / f"rig_{setting}.glb"
        _ok(_run(["-m", "artdef_addon", "fit", str(source), "--links", "4", "--residuals", setting,
                  "--glb", str(out)], cwd=tmp_path))
        runs[setting] = (out, gltf_contents(out), replay_error(source, out, frames))
    skin = runs["0"]
    assert skin[1]["targets"] == 0
    assert skin[2][1] > RMS_BAR                    # the skin alone misses: the test is not empty
    auto = runs["auto"]
    # at most a quarter of the frames, and the key that keeps their weights ≥ 0
    assert 0 < auto[1]["targets"] <= len(frames) // 4 + 1
    assert auto[2][0] < MAX_BAR and auto[2][1] < RMS_BAR
    assert runs["2"][1]["targets"] in (2, 3)
    assert runs["2"][2][1] < skin[2][1]            # two shapes already help
    messages = json.loads(_validate(auto[0]).stdout)["issues"]["messages"]
    assert not [m for m in messages if m["severity"] == 0], messages
