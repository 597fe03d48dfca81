"""Headless fits end to end: ``python -m artdef_addon fit ... --blend --glb --png``
as a subprocess, the .glb checked by the Khronos validator and read back."""

import json
import os
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO_ROOT

LINKS = 3
VALIDATOR = REPO_ROOT / ".tools" / "node_modules" / "gltf-validator"
VALIDATE_JS = REPO_ROOT / "scripts" / "validate_gltf.js"


def _run(args, cwd, timeout=600):
    env = dict(os.environ)
    env.pop("ARTDEF_TRACEBACK", None)   # the tests read the command's own output: one line on failure
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO_ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.run([sys.executable, *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _ok(proc):
    assert proc.returncode == 0, (
        f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


@pytest.fixture(scope="module")
def rod_scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("scan")
    scan = d / "rod.npz"
    _ok(_run(["-m", "artdef_addon", "sample", "rod", "-o", str(scan)], cwd=d))
    assert scan.is_file()
    return scan


@pytest.fixture(scope="module")
def fitted(rod_scan, tmp_path_factory):
    """One CLI fit of the rod writing every output (shared by the tests below)."""
    d = tmp_path_factory.mktemp("fit")
    out = {k: d / f"rod.{k}" for k in ("npz", "blend", "glb", "png")}
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(rod_scan), "--links", str(LINKS),
                     "-o", str(out["npz"]), "--blend", str(out["blend"]),
                     "--glb", str(out["glb"]), "--png", str(out["png"])], cwd=d))
    out["proc"] = proc
    return out


# ---------------------------------------------------------------- GLB reader

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16,
              5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def read_glb(path):
    """(json dict, binary chunk) of a GLB file (glTF 2.0 binary container)."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    gltf, binary, offset = None, b"", 12
    while offset < length:
        chunk_len, chunk_type = struct.unpack_from("<I4s", data, offset)
        chunk = data[offset + 8: offset + 8 + chunk_len]
        offset += 8 + chunk_len
        if chunk_type == b"JSON":
            gltf = json.loads(chunk)
        elif chunk_type == b"BIN\x00":
            binary = chunk
    assert gltf is not None, "no JSON chunk"
    return gltf, binary


def accessor(gltf, binary, index):
    acc = gltf["accessors"][index]
    view = gltf["bufferViews"][acc["bufferView"]]
    dtype = np.dtype(_COMPONENT[acc["componentType"]])
    width = _WIDTH[acc["type"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", dtype.itemsize * width)
    rows = [np.frombuffer(binary, dtype=dtype, count=width, offset=start + i * stride)
            for i in range(acc["count"])]
    return np.array(rows).reshape(acc["count"], width)


def yup_to_blender(p):
    """glTF is Y-up; Blender's exporter maps Blender (x, y, z) to (x, z, -y)."""
    return np.array([p[0], -p[2], p[1]])


# ---------------------------------------------------------------- tests

def test_fit_cli_writes_every_output(fitted):
    for key in ("npz", "blend", "glb", "png"):
        assert fitted[key].is_file() and fitted[key].stat().st_size > 0, key
    assert fitted["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    head = fitted["blend"].read_bytes()[:7]
    assert head == b"BLENDER" or head[:4] == b"\x28\xb5\x2f\xfd", head  # plain or zstd


def test_blender_stage_prints_only_the_commands_own_lines(fitted):
    """Blender's own printing in the Blender stage (operator reports naming temporary files, the
    exporters' logs, the bpy wheel's Draco/MeshOptimizer "ERROR" lines, GPU warnings on stderr)
    stays off the terminal: the command prints its summary and the files it wrote."""
    out, err = fitted["proc"].stdout, fitted["proc"].stderr
    assert "building the Blender outputs" in out and f"wrote {fitted['glb']}" in out
    for chatter in ("Draco", "glTF 2.0 export", "Info: ", ".artdef-tmp", "Saved"):
        assert chatter not in out, chatter
    assert err == ""


def test_quiet_fit_with_every_blender_output_prints_nothing(rod_scan, tmp_path):
    """``-q``: nothing on stdout or stderr on success, every output written."""
    out = {k: tmp_path / f"rod.{k}" for k in ("npz", "blend", "glb", "fbx", "png")}
    proc = _ok(_run(["-m", "artdef_addon", "fit", str(rod_scan), "--links", str(LINKS), "-q",
                     "-o", str(out["npz"]), "--blend", str(out["blend"]), "--glb", str(out["glb"]),
                     "--fbx", str(out["fbx"]), "--png", str(out["png"])], cwd=tmp_path))
    assert (proc.stdout, proc.stderr) == ("", "")
    assert all(p.is_file() and p.stat().st_size > 0 for p in out.values())


_BLEND_PROBE = """
import sys, bpy
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
arms = [o for o in bpy.data.objects if o.type == 'ARMATURE']
meshes = [o for o in bpy.data.objects if o.type == 'MESH']
assert len(arms) == 1 and len(meshes) == 1, [(o.name, o.type) for o in bpy.data.objects]
mesh, arm = meshes[0], arms[0]
print(len([b for b in arm.data.bones if b.use_deform]), len(mesh.data.vertices),
      mesh.parent == arm, mesh.find_armature() == arm)
"""


def test_blend_reopens_with_the_rig(fitted, rod_scan):
    proc = _ok(_run(["-c", _BLEND_PROBE, str(fitted["blend"])], cwd=fitted["blend"].parent))
    bones, verts, parented, deformed = proc.stdout.strip().splitlines()[-1].split()
    assert int(bones) == LINKS
    assert int(verts) == np.load(rod_scan)["vertices"].shape[0]
    assert parented == "True" and deformed == "True"


def _validate(path):
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (apt-get install nodejs): glTF validator not run")
    if not (VALIDATOR / "package.json").is_file():
        pytest.skip("gltf-validator not installed in .tools/ (scripts/test.sh installs it)")
    proc = subprocess.run([node, str(VALIDATE_JS), str(path), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode in (0, 1), proc.stderr
    issues = json.loads(proc.stdout)["issues"]
    assert issues["numErrors"] == 0, [m for m in issues["messages"] if m["severity"] == 0]
    return proc


def test_glb_passes_khronos_validator(fitted):
    proc = _validate(fitted["glb"])
    assert proc.returncode == 0


def test_glb_has_one_joint_per_link_at_the_fitted_joints(fitted, rod_scan):
    gltf, binary = read_glb(fitted["glb"])
    result = np.load(fitted["npz"])
    heads = np.asarray(result["heads"], dtype=float)
    assert heads.shape == (LINKS, 3)

    assert len(gltf.get("skins", [])) == 1, gltf.get("skins")
    skin = gltf["skins"][0]
    assert len(skin["joints"]) == LINKS, [gltf["nodes"][j].get("name") for j in skin["joints"]]
    ibm = accessor(gltf, binary, skin["inverseBindMatrices"]).reshape(-1, 4, 4)
    # glTF matrices are column-major: transpose to the usual row-major layout.
    bind = np.array([np.linalg.inv(m.T) for m in ibm])
    joints_world = np.array([yup_to_blender(m[:3, 3]) for m in bind])

    scale = np.ptp(np.load(rod_scan)["vertices"], axis=0).max()
    tol = 1e-4 * scale
    # Skin joint order need not match the result's link order: match each head.
    dist = np.linalg.norm(heads[:, None, :] - joints_world[None, :, :], axis=2)
    assert dist.min(axis=1).max() < tol, (heads, joints_world)
    assert dist.min(axis=0).max() < tol, (heads, joints_world)


def test_glb_mesh_morph_targets_and_animation(fitted, rod_scan):
    gltf, binary = read_glb(fitted["glb"])
    n_vertices = np.load(rod_scan)["vertices"].shape[0]

    skinned = [n for n in gltf["nodes"] if "mesh" in n and "skin" in n]
    assert len(skinned) == 1, "expected one skinned mesh node"
    mesh = gltf["meshes"][skinned[0]["mesh"]]
    exported = sum(gltf["accessors"][p["attributes"]["POSITION"]]["count"]
                   for p in mesh["primitives"])
    # glTF splits vertices at seams, never merges them.
    assert exported >= n_vertices
    for prim in mesh["primitives"]:
        assert {"JOINTS_0", "WEIGHTS_0"} <= set(prim["attributes"])
        assert prim.get("targets"), "no morph targets (residual shape keys)"
        weights = accessor(gltf, binary, prim["attributes"]["WEIGHTS_0"])
        np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=2e-3)

    animations = gltf.get("animations", [])
    # One animation driving joints and morph weights together: viewers play
    # one animation at a time.
    assert len(animations) == 1, [a.get("name") for a in animations]
    paths = {c["target"]["path"] for a in animations for c in a["channels"]}
    assert paths & {"rotation", "translation"}, paths   # joints move
    assert "weights" in paths, paths                    # morph weights
    times = np.concatenate([accessor(gltf, binary, s["input"]).ravel()
                            for a in animations for s in a["samplers"]])
    assert times.max() > times.min(), "animation has a single key"


@pytest.fixture(scope="module")
def greens_glb(tmp_path_factory):
    """CLI fit of the Green's-matrix rod with --glb and --blend."""
    d = tmp_path_factory.mktemp("greens")
    scan = d / "greens_rod.npz"
    _ok(_run(["-m", "artdef_addon", "sample", "greens_rod", "-o", str(scan)], cwd=d))
    out = {"scan": scan, "glb": d / "g.glb", "blend": d / "g.blend"}
    _ok(_run(["-m", "artdef_addon", "fit", str(scan), "--links", str(LINKS),
              "--glb", str(out["glb"]), "--blend", str(out["blend"])], cwd=d))
    return out


def test_greens_glb_animates_the_load_sweep(greens_glb):
    """A Green's rig is driven by load empties: the exported animation must still
    move the joints (baked from the drivers) and the morph weights."""
    _validate(greens_glb["glb"])
    gltf, binary = read_glb(greens_glb["glb"])
    joints = set(gltf["skins"][0]["joints"])
    animations = gltf.get("animations", [])
    assert len(animations) == 1, [a.get("name") for a in animations]
    anim = animations[0]
    rotating = []
    weights = []
    for ch in anim["channels"]:
        sampler = anim["samplers"][ch["sampler"]]
        node, path = ch["target"]["node"], ch["target"]["path"]
        values = accessor(gltf, binary, sampler["output"])
        if node in joints and path == "rotation":
            rotating.append(np.ptp(values, axis=0).max())
        if path == "weights":
            weights.append(np.ptp(values))
    assert len(rotating) == LINKS, "not every joint has a rotation channel"
    assert max(rotating) > 1e-3, rotating          # the joints actually turn
    assert weights and max(weights) > 0.5, weights  # residual keys go 0 -> 1 -> 0
    times = np.concatenate([accessor(gltf, binary, s["input"]).ravel() for s in anim["samplers"]])
    assert times.max() > times.min()


_GREENS_PROBE = """
import sys, bpy
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
arm = [o for o in bpy.data.objects if o.type == 'ARMATURE'][0]
loads = [o for o in bpy.data.objects if o.get("artdef_load") is not None]
print(arm.animation_data.action is None, len(arm.animation_data.drivers) > 0,
      all(o.animation_data and o.animation_data.action for o in loads),
      bpy.context.scene.frame_start, bpy.context.scene.frame_end)
"""


def test_greens_blend_keeps_live_drivers(greens_glb):
    """The export's bake is temporary: the saved rig has drivers, no baked action."""
    proc = _ok(_run(["-c", _GREENS_PROBE, str(greens_glb["blend"])], cwd=greens_glb["blend"].parent))
    no_action, drivers, swept, start, end = proc.stdout.strip().splitlines()[-1].split()
    assert no_action == "True" and drivers == "True" and swept == "True"
    m = int(np.load(greens_glb["scan"])["load_vertices"].shape[0])
    assert (int(start), int(end)) == (0, 2 * 3 * m * 10)


_KEYED_EXPORT = """
import sys, bpy
import os, runpy, artdef_addon; headless = runpy.run_path(os.path.join(os.path.dirname(os.path.dirname(artdef_addon.__file__)), 'scripts', 'artdef_fit.py'))['blender_layer']()
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
scene = bpy.context.scene
arm = [o for o in bpy.data.objects if o.type == 'ARMATURE'][0]
mesh = [o for o in bpy.data.objects if o.type == 'MESH'][0]
leaf = [pb for pb in arm.pose.bones if pb.bone.use_deform and not pb.children][0]
leaf.rotation_euler = (0.0, 0.0, 0.0)
leaf.keyframe_insert("rotation_euler", frame=scene.frame_start)
leaf.rotation_euler = (0.0, 0.0, 0.7)
leaf.keyframe_insert("rotation_euler", frame=scene.frame_start + 10)
keyed = arm.animation_data.action
headless.export_glb(sys.argv[2], mesh, arm)
print(arm.animation_data.action == keyed, len(keyed.fcurves) if hasattr(keyed, "fcurves") else -1,
      leaf.name, scene.frame_end, scene.render.fps)
"""


def test_greens_export_keeps_animator_keys_and_the_load_sweep(greens_glb, tmp_path):
    """An animator who keys a link bone of a Green's rig (on top of the loads)
    still exports the whole load sweep, with the keyed bone's extra turn; the
    animator's action is left as it was."""
    glb = tmp_path / "keyed.glb"
    proc = _ok(_run(["-c", _KEYED_EXPORT, str(greens_glb["blend"]), str(glb)], cwd=tmp_path))
    same, _, leaf, end, fps = proc.stdout.strip().splitlines()[-1].split()
    assert same == "True"
    _validate(glb)
    ref, ref_bin = read_glb(greens_glb["glb"])
    gltf, binary = read_glb(glb)
    anims = gltf.get("animations", [])
    assert len(anims) == 1
    times = np.concatenate([accessor(gltf, binary, s["input"]).ravel() for s in anims[0]["samplers"]])
    assert times.max() == pytest.approx(int(end) / int(fps), abs=1e-3)  # the whole sweep

    def leaf_rotation(g, b):
        node = [i for i, n in enumerate(g["nodes"]) if n.get("name") == leaf][0]
        a = g["animations"][0]
        ch = [c for c in a["channels"] if c["target"]["node"] == node and c["target"]["path"] == "rotation"][0]
        return accessor(g, b, a["samplers"][ch["sampler"]]["output"])

    q_ref, q = leaf_rotation(ref, ref_bin), leaf_rotation(gltf, binary)
    assert q.shape == q_ref.shape
    # frame 0: no key offset yet, same pose; frame 10 on: the keyed 0.7 rad turn on top
    np.testing.assert_allclose(np.abs(np.sum(q[0] * q_ref[0])), 1.0, atol=1e-5)
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(q[10:] * q_ref[10:], axis=1)), 0, 1))
    assert np.all(angle > 0.1), angle.min()


_GROUP_WEIGHTS = """
import sys, bpy, numpy as np
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
mesh = [o for o in bpy.data.objects if o.type == 'MESH'][0]
names = [g.name for g in mesh.vertex_groups]
w = np.zeros((len(mesh.data.vertices), len(names)))
for v in mesh.data.vertices:
    for g in v.groups:
        w[v.index, g.group] = g.weight
np.savez(sys.argv[2], weights=w, names=np.array(names))
"""


def test_a_command_leaves_nothing_in_the_temporary_folder(rod_scan, tmp_path):
    """The command exits without Blender's teardown (cli.exit_process), which would remove
    Blender's session folder (<temp>/blender_XXXXXX/): it removes it itself, as it removes the
    add-on's temporary repository; otherwise each fit writing a .glb would leave one behind."""
    temp = tmp_path / "temp"
    temp.mkdir()
    # what a run killed with SIGKILL left (the add-on's repository, with its link to the source):
    # removed by the next run, since its process no longer runs
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = temp / f"artdef-headless-repo-{dead.pid}-x1"
    stale.mkdir()
    os.symlink(REPO_ROOT, stale / "artdef", target_is_directory=True)
    env = dict(os.environ, TMPDIR=str(temp), PYTHONPATH=str(REPO_ROOT))
    proc = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", str(rod_scan), "--links", str(LINKS),
                           "--glb", str(tmp_path / "rod.glb")], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    _ok(proc)
    assert (tmp_path / "rod.glb").is_file()
    assert os.listdir(temp) == []
    assert (REPO_ROOT / "artdef_addon" / "files.py").is_file()     # the link's target untouched


def test_blend_holds_the_fit_of_the_npz_with_every_option(rod_scan, tmp_path):
    """One fit per command: ``fit -o R --blend B`` builds the .blend's rig from the result it
    saved (every option allowed, ``--strategy`` too), so the vertex groups hold the .npz's skin
    weights (to the float32 Blender stores)."""
    npz, blend = tmp_path / "r.npz", tmp_path / "r.blend"
    _ok(_run(["-m", "artdef_addon", "fit", str(rod_scan), "--links", str(LINKS), "--strategy", "paper",
              "--skin", "seam", "-o", str(npz), "--blend", str(blend)], cwd=tmp_path))
    _ok(_run(["-c", _GROUP_WEIGHTS, str(blend), str(tmp_path / "w.npz")], cwd=tmp_path))
    with np.load(npz) as r, np.load(tmp_path / "w.npz") as b:
        weights, groups = r["weights"], b["weights"]
        assert str(r["skin"]) == "seam"
    assert weights.shape[1] == LINKS and np.ptp(weights) > 0.5
    # the bones and groups are renamed (root-first): match each link's column to its group
    diff = np.abs(weights[:, :, None] - groups[:, None, :]).max(axis=0)      # (links, groups)
    match = diff.argmin(axis=1)
    assert len(set(match.tolist())) == LINKS
    np.testing.assert_allclose(groups[:, match], weights, atol=1e-6)


def test_artdef_fit_script_runs_with_the_bpy_module(rod_scan, tmp_path):
    glb = tmp_path / "script.glb"
    _ok(_run([str(REPO_ROOT / "scripts" / "artdef_fit.py"), "--", "fit", str(rod_scan),
              "--links", str(LINKS), "--glb", str(glb)], cwd=tmp_path))
    assert glb.is_file() and glb.read_bytes()[:4] == b"glTF"


def test_build_outputs_without_bpy_says_how_to_get_it(tmp_path):
    code = ("import sys; sys.modules['bpy'] = None\n"
            "import os, runpy, artdef_addon; headless = runpy.run_path(os.path.join(os.path.dirname(os.path.dirname(artdef_addon.__file__)), 'scripts', 'artdef_fit.py'))['blender_layer']()\n"
            "try:\n"
            "    headless.require_bpy()\n"
            "    raise SystemExit('require_bpy() did not raise')\n"
            "except RuntimeError as ex:\n"
            "    assert 'needs Blender' in str(ex)\n"
            "try:\n"
            "    headless.build_outputs('x.npz', None, None, None, 'x.glb', None)\n"
            "except RuntimeError as ex:\n"
            "    print(ex)\n"
            "    raise SystemExit(3)\n")
    proc = _run(["-c", code], cwd=tmp_path)
    assert proc.returncode == 3, proc.stderr
    assert "needs Blender" in proc.stdout and "bpy" in proc.stdout


def _bad_scans(rod):
    scan = dict(np.load(rod))
    v = scan["vertices"]
    flat = dict(scan, vertices=v[:, :2])                       # (N, 2) vertices
    short = dict(scan)
    if "displacements" in scan:
        short["displacements"] = scan["displacements"][:, :-1]  # one vertex short
    else:
        short["greens"] = scan["greens"][:-3]                  # one vertex short
    return {"vertices_2d": flat, "field_vertex_count": short}


@pytest.mark.parametrize("kind", ["vertices_2d", "field_vertex_count"])
def test_fit_on_wrong_shape_fails_with_one_line_and_writes_nothing(rod_scan, tmp_path, kind):
    bad = tmp_path / "bad.npz"
    np.savez(bad, **_bad_scans(rod_scan)[kind])
    outs = [tmp_path / n for n in ("r.npz", "r.blend", "r.glb", "r.png")]
    proc = _run(["-m", "artdef_addon", "fit", str(bad), "--links", str(LINKS),
                 "-o", str(outs[0]), "--blend", str(outs[1]), "--glb", str(outs[2]),
                 "--png", str(outs[3])], cwd=tmp_path, timeout=300)
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not [p.name for p in outs if p.exists()], "outputs written for a bad scan"


def test_triangles_with_a_repeated_vertex_keep_every_blender_output(rod_scan, tmp_path):
    """A scan may hold a triangle with a repeated vertex (legal, the fit keeps it); Blender's mesh
    has none. The Blender outputs label the triangles Blender kept with their own links (they
    failed with a shape mismatch before)."""
    d = dict(np.load(rod_scan, allow_pickle=False))
    T = len(d["faces"])
    d["faces"] = np.concatenate([d["faces"][:10], [[0, 0, 1]], d["faces"][10:]])
    scan = tmp_path / "degen.npz"
    np.savez(scan, **d)
    out = {k: tmp_path / f"rig.{k}" for k in ("npz", "glb", "blend")}
    _ok(_run(["-m", "artdef_addon", "fit", str(scan), "--links", str(LINKS), "-q", "-o", str(out["npz"]),
              "--glb", str(out["glb"]), "--blend", str(out["blend"])], cwd=tmp_path))
    gltf, binary = read_glb(out["glb"])
    prim = gltf["meshes"][0]["primitives"][0]
    assert accessor(gltf, binary, prim["indices"]).size == 3 * T
    assert len(gltf["skins"][0]["joints"]) == LINKS
    # the labels of the kept triangles, whatever Blender does to their corner order
    import runpy
    import artdef_addon
    entry = os.path.join(os.path.dirname(os.path.dirname(artdef_addon.__file__)), "scripts", "artdef_fit.py")
    labels_of_kept_faces = runpy.run_path(entry)["blender_layer"]().labels_of_kept_faces
    faces = np.array([[0, 1, 2], [2, 3, 4], [4, 4, 5], [1, 2, 3]])
    labels = np.array([7, 8, 9, 10])
    kept = np.array([[3, 1, 2], [4, 2, 3], [0, 1, 2]])
    assert labels_of_kept_faces(kept, faces, labels).tolist() == [10, 8, 7]
    with pytest.raises(RuntimeError, match="a triangle the scan does not"):
        labels_of_kept_faces(np.array([[0, 1, 5]]), faces, labels)


def test_rotation_only_on_a_greens_scan_is_refused_before_the_fit(greens_glb, tmp_path):
    proc = _run(["-m", "artdef_addon", "fit", str(greens_glb["scan"]), "--links", str(LINKS),
                 "--glb", str(tmp_path / "r.glb"), "--rotation-only"], cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "--rotation-only applies to tracked scans" in lines[0], proc
    assert "estimate" not in proc.stdout and not (tmp_path / "r.glb").exists()


def test_a_repeated_load_vertex_is_refused_before_the_fit_with_blender_outputs(greens_glb, tmp_path):
    """Blender holds one load point per vertex: --glb on a scan listing a vertex twice is refused with
    one line before the fit (rather than fitting, then failing in the Blender stage as an internal error);
    without Blender outputs the core still fits it."""
    d = dict(np.load(greens_glb["scan"]))
    d["load_vertices"] = np.r_[d["load_vertices"], d["load_vertices"][-1]]
    d["greens"] = np.concatenate([d["greens"], d["greens"][:, -3:]], axis=1)
    scan = tmp_path / "dup.npz"
    np.savez(scan, **d)
    proc = _run(["-m", "artdef_addon", "fit", str(scan), "--links", str(LINKS), "--glb", str(tmp_path / "d.glb")],
                cwd=tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc
    assert f"--glb: vertex {int(d['load_vertices'][-1])} is listed 2 times in load_vertices" in lines[0], lines
    assert "estimate" not in proc.stdout and not (tmp_path / "d.glb").exists()
    _ok(_run(["-m", "artdef_addon", "fit", str(scan), "--links", str(LINKS), "-q", "-o", str(tmp_path / "d.npz")],
             cwd=tmp_path))
