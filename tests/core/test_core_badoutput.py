"""Bad input never costs the user a file and always gets one clear line.

Here: outputs that would replace an input, failed or interrupted writes.

Every malformed file, unusable output path and out-of-range number ends with exit 2 and exactly one
stderr line naming the file or option; the input is never changed; a failed or interrupted write
leaves the earlier output byte-identical and no temporary behind; legal but unusual meshes fit.
"""
import errno
import os
import resource
import subprocess
import sys

import numpy as np
import pytest

from artdef_addon import cli, files, samples
from artdef_addon import result as RS

from badinput import ROOT, _no_fit, digest, leftovers, rod, rod_file, run


# ---------------------------------------------------------------- output paths
def test_output_is_the_input_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    _no_fit(monkeypatch)
    before = digest(rod_file)
    os.link(rod_file, tmp_path / "hard.npz")
    os.symlink(rod_file, tmp_path / "soft.npz")
    for argv, says in [
        (["-o", rod_file], "would overwrite the input"),
        (["-o", tmp_path / "sub" / ".." / "rod.npz"], "does not exist"),
        (["-o", tmp_path / "hard.npz"], "would overwrite the input"),
        (["-o", tmp_path / "soft.npz"], "would overwrite the input"),
        (["--blend", rod_file], "must end in .blend"),
        (["--glb", tmp_path / "x.gltf"], "must end in .glb"),
        (["--png", tmp_path / "x.jpg"], "must end in .png"),
        (["-o", tmp_path / "nodir" / "r.npz"], "does not exist"),
        (["-o", tmp_path], "is a directory"),
        (["-o", tmp_path / "a.blend", "--blend", tmp_path / "a.blend"], "name the same file"),
    ]:
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", *argv)
        assert code == 2 and len(err) == 1 and says in err[0], (argv, err)
    assert digest(rod_file) == before
    assert sorted(os.listdir(tmp_path)) == ["hard.npz", "rod.npz", "soft.npz"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into a read-only directory")
def test_read_only_directory_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    _no_fit(monkeypatch)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", ro / "r.npz")
    finally:
        ro.chmod(0o700)
    assert code == 2 and len(err) == 1 and "is not writable" in err[0]


def test_output_written_with_exactly_the_name_given(rod_file, tmp_path, capsys):
    out = tmp_path / "result.dat"
    code, stdout, err = run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")
    assert code == 0 and err == []
    assert sorted(os.listdir(tmp_path)) == ["result.dat", "rod.npz"]
    assert RS.load_result(out).n_links == 3
    code, stdout, err = run(capsys, "sample", "rod", "-o", tmp_path / "scan.bin")
    assert code == 0 and "wrote" in stdout and (tmp_path / "scan.bin").is_file()
    assert files.read_scan(tmp_path / "scan.bin").n_vertices == 297


# ---------------------------------------------------------------- failed or interrupted writes
@pytest.mark.parametrize("failure,code,says", [
    (OSError(errno.ENOSPC, "No space left on device"), 1, "No space left on device"),
    (KeyboardInterrupt(), 130, "interrupted"),
])
def test_failed_overwrite_keeps_the_earlier_result(rod_file, tmp_path, capsys, monkeypatch, failure, code, says):
    out = tmp_path / "out.npz"
    assert run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")[0] == 0
    before = digest(out)
    real = files._savez

    def half_then_fail(f, arrays, compress):
        real(f, arrays, compress)
        f.truncate(f.tell() // 2)       # a partial file, as a full disk leaves
        raise failure
    monkeypatch.setattr(files, "_savez", half_then_fail)
    got, _, err = run(capsys, "fit", rod_file, "--links", "2", "-o", out, "-q")
    assert got == code and len(err) == 1 and says in err[0], err
    assert digest(out) == before and RS.load_result(out).n_links == 3
    assert leftovers(tmp_path) == []


def test_file_size_limit_keeps_the_earlier_result(rod_file, tmp_path):
    """A real failing write: RLIMIT_FSIZE below the result's size (write → EFBIG)."""
    out = tmp_path / "out.npz"
    env = dict(os.environ, PYTHONPATH=ROOT)
    cmd = [sys.executable, "-m", "artdef_addon", "fit", str(rod_file), "--links", "3", "-q", "-o", str(out)]
    assert subprocess.run(cmd, env=env, capture_output=True, timeout=300).returncode == 0
    before = digest(out)
    cmd[cmd.index("3")] = "2"

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, preexec_fn=limit)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1 and "File too large" in lines[0], p.stderr
    assert digest(out) == before and leftovers(tmp_path) == []


def test_ctrl_c_during_the_fit(tmp_path, interrupt_at):
    scan = tmp_path / "br.npz"
    files.write_scan(scan, samples.make("branching"))
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    code, err = interrupt_at([sys.executable, "-m", "artdef_addon", "fit", str(scan), "--links", "auto",
                              "-o", str(out)], "estimate:", tmp_path)
    lines = err.strip().splitlines()
    assert code == 130 and lines == ["artdef: error: interrupted; no file was written or changed"], err
    assert out.read_bytes() == b"earlier result" and leftovers(tmp_path) == []


def test_setup_on_a_full_disk_says_so_before_creating_anything(tmp_path):
    """scripts/env.sh (the README's commands' set-up) checks the free space before it creates or
    fills a virtual environment: one line naming the disk and the space, exit 1, nothing created
    (pip would otherwise stop half-way with 'No space left on device')."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    (tmp_path / "scripts").mkdir()
    for name in ("requirements.txt", "requirements-dev.txt", "requirements-4.5.txt"):
        (tmp_path / name).write_bytes(open(os.path.join(root, name), "rb").read())
    (tmp_path / "scripts" / "env.sh").write_bytes(open(os.path.join(root, "scripts", "env.sh"), "rb").read())
    before = sorted(os.listdir(tmp_path))
    env = dict(os.environ, ARTDEF_ENV_NEED_MB=str(2 ** 40))
    for what in ("dev", "4.5"):
        run = subprocess.run(["bash", str(tmp_path / "scripts" / "env.sh"), what], env=env,
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 1
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and "MB free on the disk of" in lines[0] and "free some space" in lines[0]
        assert sorted(os.listdir(tmp_path)) == before


# ---------------------------------------------------------------- files a run reads, files it replaces
def test_output_may_not_replace_a_file_of_an_input_sequence_or_gltf(rod_file, tmp_path, capsys, monkeypatch):
    """The "not an input" check covers every file a run reads: each OBJ/PLY of a sequence's folder
    (given as the folder, a pattern or one numbered file) and a .gltf's external buffers and images.
    Refused with one line before any work; the files stay byte-identical."""
    _no_fit(monkeypatch)
    seq = tmp_path / "seq"
    seq.mkdir()
    for n in range(4):
        (seq / f"pose_{n:03d}.obj").write_text(f"v {n} 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    gl = tmp_path / "gl"
    gl.mkdir()
    (gl / "data.bin").write_bytes(b"\0" * 64)
    (gl / "tex a.png").write_bytes(b"png")
    (gl / "model.gltf").write_text('{"asset": {"version": "2.0"}, "buffers": [{"uri": "data.bin", "byteLength": 64}],'
                                   ' "images": [{"uri": "tex%20a.png"}, {"uri": "data:image/png;base64,AA=="}]}')
    before = {p: digest(p) for p in list(seq.iterdir()) + list(gl.iterdir())}
    for scan, out in [(seq, seq / "pose_002.obj"), (seq / "pose_000.obj", seq / "pose_003.obj"),
                      (str(seq / "pose_*.obj"), seq / "pose_001.obj"), (gl / "model.gltf", gl / "data.bin"),
                      (gl / "model.gltf", gl / "tex a.png")]:
        code, _, err = run(capsys, "fit", scan, "--links", "3", "-o", out)
        assert code == 2 and len(err) == 1 and "would overwrite the input file" in err[0], (scan, out, err)
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "--clip", seq, "-o", seq / "pose_001.obj")
    assert code == 2 and len(err) == 1 and "would overwrite the input file" in err[0], err
    assert {p: digest(p) for p in before} == before
    assert sorted(os.listdir(gl)) == ["data.bin", "model.gltf", "tex a.png"]


def test_outputs_are_replaced_all_or_nothing(tmp_path):
    """files.Outputs.commit: when a later rename fails, the files already replaced are put back,
    the error names the user's file (not a temporary), and nothing temporary is left."""
    first, second = tmp_path / "a.npz", tmp_path / "b.npz"
    first.write_bytes(b"earlier a")
    second.mkdir()                        # a rename onto a non-empty directory fails
    (second / "keep").write_text("x")
    out = files.Outputs()
    with out:
        files._savez(open(out.path(first), "wb"), {"x": np.arange(3)}, False)
        with open(out.path(second), "wb") as f:
            f.write(b"new b")
        with pytest.raises(OSError) as info:
            out.commit()
    assert info.value.filename == str(second)
    assert first.read_bytes() == b"earlier a" and out.committed == []
    assert leftovers(tmp_path) == []
    # a file that did not exist before is removed again
    third = tmp_path / "c.npz"
    out = files.Outputs()
    with out:
        with open(out.path(third), "wb") as f:
            f.write(b"new c")
        with open(out.path(second), "wb") as f:
            f.write(b"new b")
        with pytest.raises(OSError):
            out.commit()
    assert not third.exists() and leftovers(tmp_path) == []


def test_replaced_outputs_keep_their_permissions_and_links(rod_file, tmp_path, capsys):
    """An output replaced keeps its permission bits (a private result stays private); an output
    path that is a symbolic link is written through: the link stays, its target is replaced."""
    private = tmp_path / "private.npz"
    private.write_bytes(b"old")
    private.chmod(0o600)
    target = tmp_path / "target.npz"
    target.write_bytes(b"old")
    link = tmp_path / "link.npz"
    os.symlink(target, link)
    for out in (private, link):
        code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", out, "-q")
        assert code == 0 and err == [], err
    assert (private.stat().st_mode & 0o777) == 0o600 and RS.load_result(private).n_links == 3
    assert os.path.islink(link) and os.readlink(link) == str(target) and RS.load_result(target).n_links == 3
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", "/dev/stdout")
    assert code == 2 and len(err) == 1 and "not a regular file" in err[0], err
    assert leftovers(tmp_path) == []


def test_sigterm_during_the_fit(tmp_path, interrupt_at):
    """``kill`` / ``timeout`` / a cancelled job (SIGTERM): one line, exit 143, the earlier output
    byte-identical and no temporary left, as for Ctrl-C."""
    import signal
    scan = tmp_path / "br.npz"
    files.write_scan(scan, samples.make("branching"))
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    code, err = interrupt_at([sys.executable, "-m", "artdef_addon", "fit", str(scan), "--links", "auto",
                              "-o", str(out)], "estimate:", tmp_path, sig=signal.SIGTERM)
    lines = err.strip().splitlines()
    assert code == 143 and lines == ["artdef: error: terminated; no file was written or changed"], err
    assert out.read_bytes() == b"earlier result" and leftovers(tmp_path) == []


def test_a_killed_runs_temporaries_are_removed_by_the_next(rod_file, tmp_path, capsys):
    """SIGKILL (or the out-of-memory killer) leaves an output's hidden temporary folder: the next
    command writing there removes those of processes that no longer run, and no other."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".artdef-tmp-{dead.pid}-x1"
    stale.mkdir()
    (stale / "out.npz").write_bytes(b"partial")
    alive = tmp_path / f".artdef-tmp-{os.getppid()}-x2"       # a running process's
    alive.mkdir()
    legacy = tmp_path / ".artdef-tmp-abcdef"                    # no process number: left alone
    legacy.mkdir()
    code, _, err = run(capsys, "fit", rod_file, "--links", "3", "-o", tmp_path / "out.npz", "-q")
    assert code == 0 and err == []
    assert not stale.exists() and alive.is_dir() and legacy.is_dir()
    assert RS.load_result(tmp_path / "out.npz").n_links == 3


@pytest.mark.parametrize("links", ["3", "auto"])
def test_stdout_closed_early_still_writes_the_outputs(rod_file, tmp_path, links):
    """``fit ... | head -1``: the reader closing the pipe costs no output; no traceback, exit 0.
    (The pipe is closed before the command prints anything, so every line it prints meets it.)"""
    out = tmp_path / "out.npz"
    out.write_bytes(b"earlier result")
    env = dict(os.environ, PYTHONPATH=ROOT)
    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run([sys.executable, "-m", "artdef_addon", "fit", str(rod_file), "--links", links,
                            "-o", str(out)], stdout=w, stderr=subprocess.PIPE, env=env, text=True,
                           timeout=300)
    finally:
        os.close(w)
    assert p.returncode == 0 and p.stderr == "", p.stderr
    assert RS.load_result(out).n_links >= 1 and leftovers(tmp_path) == []

def test_too_long_output_name_is_refused_before_work(rod_file, tmp_path, capsys, monkeypatch):
    """A file name longer than the file system allows was found only when writing, after the fit:
    exit 1 and a line naming the hidden temporary (.artdef-tmp-.../xxx), not the user's path."""
    _no_fit(monkeypatch)
    out = tmp_path / ("x" * 300 + ".npz")
    for argv in (["fit", rod_file, "--links", "3", "-o", out], ["sample", "rod", "-o", out]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and len(err) == 1 and "the file name is 304 bytes long" in err[0], err
        assert ".artdef-tmp" not in err[0] and leftovers(tmp_path) == []


@pytest.mark.skipif(sys.platform != "linux", reason="a file name that is not UTF-8 (POSIX bytes)")
def test_a_name_blender_cannot_hold_is_refused_before_work(rod, tmp_path, capsys, monkeypatch):
    """A scan or an output named in bytes that are not UTF-8 reached Blender after the fit: exit 1,
    'internal error: TypeError: BlendDataMeshes.new(): ... surrogates not allowed'."""
    bad = os.fsdecode(b"r\xe9")
    files.write_scan(tmp_path / (bad + ".npz"), rod)
    files.write_scan(tmp_path / "rod.npz", rod)
    _no_fit(monkeypatch)
    fake = type("Headless", (), {"require_bpy": staticmethod(lambda: None),
                                 "build_outputs": staticmethod(lambda *a, **k: pytest.fail("Blender ran"))})
    for scan, blend in ((bad + ".npz", "o.blend"), ("rod.npz", bad + ".blend")):
        code, _, err = run(capsys, "fit", tmp_path / scan, "--links", "3", "--blend", tmp_path / blend, blender=fake)
        assert code == 2 and len(err) == 1 and "r\\xe9" in err[0] and "not: rename it" in err[0], err
    assert sorted(os.listdir(tmp_path)) == sorted([bad + ".npz", "rod.npz"])
