"""The file boundary: every file artdef reads is read and checked here, every file it writes is
written here (atomically).

Reading
    :func:`read_npz` opens a ``.npz`` without unpickling and without trusting it: the first bytes
    say what the file is (a zip, a bare ``.npy``, text), every member's ``.npy`` header is read and
    its declared size checked against the member's stored size *before* any array is allocated
    (a header declaring an enormous array, a truncated member), and any decoding failure becomes
    one :class:`BadFile` line naming the file and the problem. :func:`read_scan` and
    :func:`read_result` add the checks of their formats (README, "Scan format" / "Result file");
    ``artdef_addon.load_scan`` is :func:`read_scan` and ``fit.load_result`` goes through
    :func:`read_result_arrays`, so the command line and the Blender import operators apply the
    same rules.

Writing
    :func:`check_outputs` runs before any work: each output's directory exists and is writable,
    no output is an input or another output (``os.path.samefile`` and ``realpath``), each has the
    extension its writer needs. :class:`Outputs` then hands out temporary paths in the target
    directories and renames them into place only on :meth:`Outputs.commit` (after fsync), so a
    failed or interrupted run (an exception, Ctrl-C, a full disk) leaves every earlier file
    byte-identical and no partial file. A file is written with exactly the name given (numpy's
    ``savez`` would append ``.npz`` to a path; it is handed an open file instead).
"""
from __future__ import annotations

import math
import os
import shutil
import stat
import signal
import tempfile
import zipfile

import numpy as np

from . import scan as S
from .scan import ScanError

#: the largest array a scan or result member may declare, as a multiple of the member's stored
#: (uncompressed) size: a correct member holds exactly its header plus the data
_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
#: deflate cannot expand more than ~1032:1; a member claiming more is damaged or a zip bomb
_MAX_RATIO = 1100


class BadFile(ScanError):
    """A file that cannot be used; the message is one line naming the file and the problem.

    A :class:`~artdef_addon.scan.ScanError` (hence a ``ValueError``), so every caller that
    reports bad scans reports these the same way."""


class OutputError(ValueError):
    """An output path that cannot be written (checked before any work); one line."""


def _line(text) -> str:
    s = " ".join(str(text).split())
    return s or "unknown problem"


def _name(path) -> str:
    return os.fspath(path)


# ---------------------------------------------------------------- reading
def _sniff(path) -> None:
    """BadFile unless ``path`` is a readable regular file that starts like a zip archive."""
    name = _name(path)
    if not os.path.exists(path):
        raise BadFile(f"{name}: no such file")
    if os.path.isdir(path):
        raise BadFile(f"{name}: is a directory, not a .npz file")
    if not os.path.isfile(path):
        raise BadFile(f"{name}: not a regular file")
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise BadFile(f"{name}: cannot read: {exc.strerror or exc}") from None
    if not head:
        raise BadFile(f"{name}: the file is empty")
    if head.startswith(_NPY_MAGIC):
        raise BadFile(f"{name}: a single .npy array saved under another name, not a .npz archive "
                      "(save with numpy.savez)")
    if head.startswith(b"\x1f\x8b"):
        raise BadFile(f"{name}: a gzip-compressed file, not a .npz archive (decompress it with gunzip first; "
                      "numpy.savez_compressed writes a .npz that is read as it is)")
    if not head.startswith(_ZIP_MAGIC):
        printable = all(32 <= b < 127 or b in b"\t\r\n" for b in head)
        raise BadFile(f"{name}: " + ("a text file, not a .npz archive" if printable
                                     else "not a .npz archive (it does not start like a zip file)"))


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, name: str) -> np.ndarray:
    key = info.filename[:-4]
    if info.compress_size and info.file_size > _MAX_RATIO * info.compress_size + 4096:
        raise BadFile(f"{name}: member '{key}' claims {info.file_size:,} bytes from "
                      f"{info.compress_size:,} compressed: damaged")
    with zf.open(info) as fp:
        version = np.lib.format.read_magic(fp)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fp)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fp)
        else:
            raise BadFile(f"{name}: member '{key}' has an unsupported .npy version {version}")
        if dtype.hasobject:
            raise BadFile(f"{name}: member '{key}' holds Python objects (pickled data), which are "
                          "never loaded")
        if dtype.kind not in "biufcUS":
            raise BadFile(f"{name}: member '{key}' holds {dtype} values; scans and results hold numbers "
                          "and text")
        count = math.prod(shape)
        need = count * dtype.itemsize
        have = info.file_size - fp.tell()
        if need > have:
            raise BadFile(f"{name}: member '{key}' declares shape {tuple(shape)} {dtype} "
                          f"({need:,} bytes) but holds {max(have, 0):,} bytes: truncated or damaged")
        if count == 0:
            return np.zeros(shape, dtype=dtype)
        arr = np.empty(count, dtype=dtype)          # allocated only now, its size checked
        view = memoryview(arr).cast("B")
        got = 0
        while got < need:     # 1 MB reads (benchmarks/results/core_constants.md)
            data = fp.read(min(1 << 20, need - got))
            if not data:
                raise BadFile(f"{name}: member '{key}' is truncated")
            view[got:got + len(data)] = data
            got += len(data)
        if fortran:
            return arr.reshape(shape[::-1]).transpose()
        return arr.reshape(shape)


def read_npz(path) -> dict:
    """The arrays of a ``.npz`` file as a dict, never unpickling. Any problem → :class:`BadFile`
    (one line: the file and the problem). Sizes are checked against the archive before any
    array is allocated."""
    name = _name(path)
    _sniff(path)
    out = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                if info.is_dir():
                    continue
                if not info.filename.endswith(".npy"):
                    raise BadFile(f"{name}: member '{info.filename}' is not a .npy array")
                out[info.filename[:-4]] = _read_member(zf, info, name)
    except BadFile:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError) as exc:
        raise BadFile(f"{name}: damaged or truncated .npz archive ({_line(exc)})") from None
    except MemoryError:
        raise BadFile(f"{name}: an array is too large for this machine's memory") from None
    except OSError as exc:
        raise BadFile(f"{name}: cannot read: {_line(exc.strerror or exc)}") from None
    except Exception as exc:   # zlib.error, bad .npy header (ValueError/SyntaxError), CRC, ...
        raise BadFile(f"{name}: damaged .npz archive ({type(exc).__name__}: {_line(exc)})") from None
    return out


def _numeric_scalar(name, d, key, default=None, kinds="fiu"):
    if key not in d:
        if default is None:
            raise BadFile(f"{name}: no '{key}' value")
        return default
    a = d[key]
    if a.dtype.kind not in kinds or a.size != 1:
        raise BadFile(f"{name}: '{key}' must be a single number, got {a.dtype} of shape {a.shape}")
    return float(a.reshape(()))


def _check_version(name, d, what) -> None:
    """BadFile unless ``format_version`` (optional: absent means 1) is a version this artdef reads: a
    whole number from 1 to ``scan.FORMAT_VERSION`` (NaN and infinity are no version)."""
    version = _numeric_scalar(name, d, "format_version", float(S.FORMAT_VERSION))
    if not math.isfinite(version) or version != int(version) or version < 1:
        raise BadFile(f"{name}: 'format_version' is {version:g}, not a {what} format version "
                      f"(a whole number from 1; this artdef reads {S.FORMAT_VERSION})")
    if version > S.FORMAT_VERSION:
        raise BadFile(f"{name}: {what} format version {version:g} is newer than this artdef reads "
                      f"({S.FORMAT_VERSION})")


def read_scan(path):
    """Read and validate a scan file (format v1, ``scan`` module docstring) → ``Scan``.

    Every problem is one :class:`BadFile` line naming the file. Degenerate triangles (zero area,
    repeated vertices) are legal and recorded in ``degenerate_faces`` (docs/method_notes.md §2)."""
    name = _name(path)
    d = read_npz(path)
    if "face_labels" in d and "vertices" not in d:
        raise BadFile(f"{name}: a fit result, not a scan")
    for key in ("vertices", "faces"):
        if key not in d:
            found = ", ".join(sorted(d)) or "nothing"
            raise BadFile(f"{name}: no '{key}' array (the file holds: {found})")
    probe = _numeric_scalar(name, d, "probe_load", 1.0)
    _check_version(name, d, "scan")
    try:
        return S.validate_scan(S.Scan(
            vertices=d["vertices"], faces=d["faces"],
            greens=d.get("greens"), displacements=d.get("displacements"),
            load_vertices=d.get("load_vertices"), support_vertices=d.get("support_vertices"),
            probe_load=probe))
    except BadFile:
        raise
    except ScanError as exc:
        raise BadFile(f"{name}: {_line(exc)}") from None
    except MemoryError:
        raise BadFile(f"{name}: too large for this machine's memory") from None


#: result keys: (dtype kinds, ndim); L links, T triangles, N vertices, P fields
_RESULT_ARRAYS = {
    "face_labels": ("iu", 1), "parents": ("iu", 1), "joints": ("f", 2), "joint_errors": ("f", 1),
    "heads": ("f", 2), "tails": ("f", 2), "frames": ("f", 3), "grounded": ("b", 1),
    "weights": ("f", 2), "rotations": ("f", 4), "translations": ("f", 3), "angles": ("f", 3),
    "locations": ("f", 3), "residual": ("f", 3), "link_residuals": ("f", 2)}
_RESULT_SCALARS = ("rms_articulation", "rms_total", "articulation_error_percent", "probe_load", "p_max")


def _check_result_arrays(name, d, prefix=""):
    for key, (kinds, ndim) in _RESULT_ARRAYS.items():
        k = prefix + key
        if k not in d:
            raise BadFile(f"{name}: a result needs '{k}', which is missing")
        a = d[k]
        if a.dtype.kind not in kinds or a.ndim != ndim:
            raise BadFile(f"{name}: '{k}' must be a {ndim}-D {'integer' if kinds == 'iu' else 'float' if kinds == 'f' else 'bool'} "
                          f"array, got {a.dtype} of shape {a.shape}")
    L = d[prefix + "parents"].shape[0]
    for key in ("joints", "joint_errors", "heads", "tails", "frames", "grounded"):
        if d[prefix + key].shape[0] != L:
            raise BadFile(f"{name}: '{prefix + key}' has {d[prefix + key].shape[0]} rows for {L} links")
    if d[prefix + "weights"].shape[1] < L:
        raise BadFile(f"{name}: '{prefix}weights' has {d[prefix + 'weights'].shape[1]} columns for {L} links")
    fl = d[prefix + "face_labels"]
    par = d[prefix + "parents"]
    if fl.size and (fl.min() < -1 or fl.max() >= L) or par.size and (par.min() < -1 or par.max() >= L):
        raise BadFile(f"{name}: '{prefix}face_labels' or '{prefix}parents' refer to links that do not exist")


def read_result_arrays(path) -> dict:
    """Read a result file written by ``fit.save_result`` and check its keys, dtypes and shapes
    → its arrays (``fit.load_result`` makes the ``FitResult``; this module does not import the
    fit). Any problem is one :class:`BadFile` line naming the file."""
    name = _name(path)
    d = read_npz(path)
    if "face_labels" not in d and "vertices" in d:
        raise BadFile(f"{name}: a scan, not a fit result")
    _check_version(name, d, "result")      # results carry none so far; one that does is checked
    _check_result_arrays(name, d)
    for key in _RESULT_SCALARS:
        _numeric_scalar(name, d, key)
    for key in ("mode", "motion"):
        if key not in d or d[key].dtype.kind != "U" or d[key].size != 1:
            raise BadFile(f"{name}: a result needs the text value '{key}'")
    for key, kind in (("timing_names", "U"), ("timing_seconds", "f")):
        if key not in d or d[key].dtype.kind != kind or d[key].ndim != 1:
            raise BadFile(f"{name}: a result needs the 1-D array '{key}'")
    if d["timing_names"].shape != d["timing_seconds"].shape:
        raise BadFile(f"{name}: 'timing_names' and 'timing_seconds' differ in length")
    k = 0
    while f"pseudo{k}_face_labels" in d:
        _check_result_arrays(name, d, f"pseudo{k}_")
        k += 1
    return d


# ---------------------------------------------------------------- writing
#: the extension each kind of output must carry (its writer decides the format by it)
OUTPUT_EXTENSIONS = {"--blend": ".blend", "--glb": ".glb", "--fbx": ".fbx", "--png": ".png"}


def same_file(a: str, b: str) -> bool:
    """True when the paths ``a`` and ``b`` name one file (by ``realpath``, or ``os.path.samefile`` for
    hard links); False when either cannot be examined."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _special_hop(path: str) -> str | None:
    """The first step of ``path``'s chain of symbolic links (itself included) in /dev or /proc, or
    None: ``/dev/stdout`` and ``/proc/self/fd/1`` resolve to whatever the shell redirected, which
    must not be replaced by an output."""
    hop = os.path.abspath(path)
    for _ in range(40):
        if hop.startswith(("/dev/", "/proc/")):
            return hop
        if not os.path.islink(hop):
            return None
        hop = os.path.abspath(os.path.join(os.path.dirname(hop), os.readlink(hop)))
    return None


def check_outputs(inputs, outputs: dict) -> None:
    """Refuse, before any work, outputs that cannot be written or would destroy a file.

    ``inputs``: paths read by the run; ``outputs``: ``{option: path or None}``. Each output's
    directory must exist and be writable, the path must not be a directory or a special file,
    must not be an input or another output, and (for the options in
    :data:`OUTPUT_EXTENSIONS`) must carry its writer's extension. :class:`OutputError` otherwise.
    """
    given = [(opt, os.fspath(p)) for opt, p in outputs.items() if p is not None]
    for opt, p in given:
        if not p.strip():
            raise OutputError(f"{opt}: empty output path")
        want = OUTPUT_EXTENSIONS.get(opt)
        if want and os.path.splitext(p)[1].lower() != want:
            raise OutputError(f"{opt} {p}: the file name must end in {want}")
        if os.path.isdir(p):
            raise OutputError(f"{opt} {p}: is a directory")
        if os.path.exists(p) and not os.path.isfile(p):
            raise OutputError(f"{opt} {p}: exists and is not a regular file")
        # a symbolic link is written through (Outputs.path): its target is the file replaced
        target = os.path.realpath(p) if os.path.islink(p) else p
        special = _special_hop(p)
        if special:
            raise OutputError(f"{opt} {p}: leads to {special}, not a regular file; give a file's path")
        # the directory as the OS resolves it (no lexical normalising: "missing/../in.npz" is not
        # a path to "in.npz" for the OS, and must not become one here)
        d = os.path.dirname(target) or "."
        if not os.path.isdir(d):
            raise OutputError(f"{opt} {p}: the directory {d} does not exist")
        if not os.access(d, os.W_OK | os.X_OK):
            raise OutputError(f"{opt} {p}: the directory {d} is not writable")
        longest = _name_max(d)
        size = len(os.fsencode(os.path.basename(target)))
        if size > longest:      # else found only when writing, after the fit, naming the temporary
            raise OutputError(f"{opt} {p}: the file name is {size} bytes long; the file system of {d} "
                              f"allows {longest}")
        for q in inputs:
            if q is not None and os.path.exists(p) and same_file(p, os.fspath(q)):
                raise OutputError(f"{opt} {p}: would overwrite the input file; choose another output name")
    for i, (o1, p1) in enumerate(given):
        for o2, p2 in given[:i]:
            if os.path.realpath(p1) == os.path.realpath(p2) or (os.path.exists(p1) and same_file(p1, p2)):
                raise OutputError(f"{o2} and {o1} name the same file {p1}")


def _name_max(folder: str) -> int:
    """The longest file name (bytes) the file system of ``folder`` allows (255 if it cannot say)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError, TypeError):     # no pathconf (Windows), unknown
        return 255


#: the hidden folder next to an output that holds its temporary (``.artdef-tmp-<pid>-<random>``)
TEMP_PREFIX = ".artdef-tmp-"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:             # another user's process, or no way to ask: it may be running
        return True
    return True


def remove_stale(folder: str, prefix: str) -> list:
    """Remove the folders ``<prefix><pid>-*`` in ``folder`` whose process no longer runs: what a
    process killed with SIGKILL (or by the out-of-memory killer, which no clean-up survives) left
    behind. POSIX only (on Windows ``os.kill`` would end the process it asks about); folders of a
    running process, of this one, or named without a process number are left alone. Returns the
    folders removed."""
    if os.name != "posix":
        return []
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    gone = []
    for name in names:
        pid = name[len(prefix):].split("-", 1)[0] if name.startswith(prefix) else ""
        if not pid.isdigit() or int(pid) == os.getpid() or _running(int(pid)):
            continue
        path = os.path.join(folder, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
            gone.append(path)
    return gone


class Outputs:
    """Files written all-or-nothing: :meth:`path` gives a temporary path with the final file name
    inside a hidden directory next to the target; :meth:`commit` fsyncs and renames every one
    into place (``os.replace``, atomic on one file system); leaving the ``with`` block without
    committing (an exception, Ctrl-C) removes the temporaries, so earlier files stay byte-identical.
    """

    def __init__(self):
        self._pending = []      # (temp path, final path, temp dir)
        #: the final paths replaced so far by :meth:`commit` (all of them once it returns; those a
        #: failure could not restore if it raises)
        self.committed = []

    def __enter__(self):
        return self

    def path(self, final) -> str:
        """A temporary path for the output ``final``. A ``final`` that is a symbolic link is written
        through: the link's target is replaced, the link stays (as an editor saves)."""
        final = os.fspath(final)
        if os.path.islink(final):
            final = os.path.realpath(final)
        folder = os.path.dirname(final) or "."
        remove_stale(folder, TEMP_PREFIX)
        tmpdir = tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-", dir=folder)
        tmp = os.path.join(tmpdir, os.path.basename(final))
        self._pending.append((tmp, final, tmpdir))
        return tmp

    def write_npz(self, final, arrays: dict, compress: bool = False) -> str:
        """Write ``arrays`` as ``.npz`` with exactly the name ``final`` (on commit)."""
        tmp = self.path(final)
        with open(tmp, "wb") as f:
            _savez(f, arrays, compress)
        return tmp

    def commit(self) -> list:
        """Move every written temporary into place; returns the final paths.

        All or nothing: each file replaced is first kept as a hard link in its temporary
        directory, so that when a later rename fails (a file another user owns in a sticky
        directory, an immutable file) the ones already replaced are put back and the error names
        the user's file. SIGINT and SIGTERM are held off while renaming (and delivered after), so
        neither leaves the set half replaced. The replaced files keep their permission bits. :attr:`committed` lists the
        finals replaced (a file whose old version could not be kept, on a file system without
        hard links, stays listed after a failure)."""
        for tmp, final, _ in self._pending:
            if not os.path.isfile(tmp):
                raise OSError(f"nothing was written for {final}")
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        caught = []
        old = _hold_sigint(caught)
        done = []                   # (final, kept old version or None, existed before)
        try:
            try:
                for tmp, final, tmpdir in self._pending:
                    existed = os.path.lexists(final)
                    kept = None
                    if existed:
                        _keep_mode(final, tmp)
                        kept = os.path.join(tmpdir, ".artdef-previous")
                        try:
                            os.link(final, kept)
                        except OSError:
                            kept = None
                    try:
                        os.replace(tmp, final)
                    except OSError as exc:
                        raise OSError(exc.errno, exc.strerror, final) from None
                    done.append((final, kept, existed))
                    self.committed.append(final)
                    _fsync_dir(os.path.dirname(final) or ".")
            except OSError:
                for final, kept, existed in reversed(done):
                    try:
                        if kept is not None:
                            os.replace(kept, final)
                        elif not existed:
                            os.remove(final)
                        else:
                            continue        # no old version to put back: it stays listed
                        self.committed.remove(final)
                    except OSError:
                        pass
                raise
        finally:
            self._cleanup()
            _release_sigint(old)
        if caught:
            if signal.SIGINT not in caught and signal.getsignal(caught[0]) not in (signal.SIG_DFL, signal.SIG_IGN,
                                                                                    None):
                os.kill(os.getpid(), caught[0])     # the caller's own handler (cli: "terminated")
            raise KeyboardInterrupt
        return list(self.committed)

    def _cleanup(self):
        for _, _, tmpdir in self._pending:
            shutil.rmtree(tmpdir, ignore_errors=True)
        self._pending = []

    def __exit__(self, *exc):
        self._cleanup()
        return False


def _savez(f, arrays: dict, compress: bool) -> None:
    """``np.savez`` into the open file ``f``, with the archive closed on any exception (numpy 1.26's
    savez leaves its ZipFile to the garbage collector, which then printed an "Exception ignored"
    traceback after a failed write, e.g. on a full disk)."""
    mode = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(f, mode="w", compression=mode, allowZip64=True) as zf:
        for key, value in arrays.items():
            with zf.open(key + ".npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


def _keep_mode(final: str, tmp: str) -> None:
    """Give ``tmp`` the permission bits of the file it replaces (a private 0600 result stays private)."""
    try:
        os.chmod(tmp, stat.S_IMODE(os.stat(final).st_mode))
    except OSError:
        pass


def _fsync_dir(d):
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


#: the signals held off while a set of outputs is renamed into place (Ctrl-C, and the SIGTERM of
#: ``kill``, ``timeout`` or a cancelled CI job)
HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _hold_sigint(caught: list):
    """Hold off :data:`HELD_SIGNALS` (their numbers go to ``caught``); returns the old handlers,
    or None off the main thread (where no handler can be set)."""
    old = {}
    try:
        for sig in HELD_SIGNALS:
            old[sig] = signal.signal(sig, lambda signum, frame: caught.append(signum))
    except ValueError:      # not the main thread
        for sig, handler in old.items():
            signal.signal(sig, handler)
        return None
    return old


def _release_sigint(old):
    if old is not None:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def write_npz(path, arrays: dict, compress: bool = False) -> None:
    """Write one ``.npz`` atomically with exactly the name ``path``."""
    with Outputs() as out:
        out.write_npz(path, arrays, compress)
        out.commit()


def scan_arrays(scan) -> dict:
    """The members of ``scan`` in format v1 (``scan`` module docstring): float64 positions and
    fields, int64 indices, the format version."""
    out = {"format_version": np.int64(S.FORMAT_VERSION),
           "vertices": np.asarray(scan.vertices, dtype=np.float64),
           "faces": np.asarray(scan.faces, dtype=np.int64),
           "probe_load": np.float64(scan.probe_load)}
    for key, dtype in (("greens", np.float64), ("displacements", np.float64),
                       ("load_vertices", np.int64), ("support_vertices", np.int64)):
        value = getattr(scan, key)
        if value is not None:
            out[key] = np.asarray(value, dtype=dtype)
    return out


def write_scan(path, scan, compress: bool = False) -> None:
    """Write ``scan`` in format v1, atomically, with exactly the name ``path``.

    Uncompressed by default: measured fields barely compress and decompressing slows loading
    (``benchmarks/results/core_constants.md``)."""
    write_npz(path, scan_arrays(scan), compress)
