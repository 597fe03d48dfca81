"""Shared fixtures.

Import order matters: Blender reads ``BLENDER_USER_RESOURCES`` once, when
``bpy`` is first imported, so it is set here at import time (pytest imports
conftest before collecting any test module).  Every test session gets its own
throw-away user directory: installed extensions, preferences and the wheels'
site-packages never touch the developer's real Blender set-up, and subprocesses
started by tests inherit it.

``bpy`` itself is imported lazily inside the fixtures, so tests of the pure
numerical core (``artdef_addon``) run without paying for it.
"""

import atexit
import importlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

_USER_DIR = tempfile.mkdtemp(prefix="artdef-blender-user-")
os.environ["BLENDER_USER_RESOURCES"] = _USER_DIR
atexit.register(shutil.rmtree, _USER_DIR, ignore_errors=True)

REPO_ROOT = Path(__file__).resolve().parent.parent
EXT_ID = "artdef"
ADDON_MODULE = f"bl_ext.user_default.{EXT_ID}"
PLATFORM = "linux-x64"

#: The scipy the zip bundles for each Python that Blender embeds (see
#: blender_manifest.toml): Blender 4.5 LTS/5.0 run Python 3.11, 5.1+ Python 3.13.
BUNDLED_SCIPY = {(3, 11): "1.15.3", (3, 13): "1.16.3"}
PYTHON_TAG = f"python{sys.version_info[0]}.{sys.version_info[1]}"

# Directories and files at the repository root that are not part of the
# extension (mirror of [build] paths_exclude_pattern): a change in them does
# not make dist/ stale.
_NOT_PACKAGED = {
    ".git", ".venv", ".venv-4.5", ".ci", ".tools", "tests", "benchmarks", "scripts", "dist",
    "out", "wheels-cache", "node_modules", "docs", "__pycache__", ".pytest_cache",
}


def _manifest_version():
    import tomllib

    with open(REPO_ROOT / "blender_manifest.toml", "rb") as f:
        return tomllib.load(f)["version"]


def _zip_name():
    return f"{EXT_ID}-{_manifest_version()}-{PLATFORM.replace('-', '_')}.zip"


def _newest_source_mtime():
    newest = 0.0
    for dirpath, dirnames, filenames in os.walk(REPO_ROOT):
        if Path(dirpath) == REPO_ROOT:
            dirnames[:] = [d for d in dirnames if d not in _NOT_PACKAGED]
        else:
            dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        for name in filenames:
            if name.endswith((".pyc", ".zip")):
                continue
            try:
                newest = max(newest, os.stat(os.path.join(dirpath, name)).st_mtime)
            except FileNotFoundError:  # a file removed while walking (an editor's swap file)
                pass
    return newest


def build_extension(out_dir):
    """Run scripts/build_extension.sh into out_dir; return the linux-x64 zip."""
    env = dict(os.environ, ARTDEF_DIST=str(out_dir), PYTHON=sys.executable)
    proc = subprocess.run(
        ["bash", str(REPO_ROOT / "scripts" / "build_extension.sh")],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"build_extension.sh failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    zip_path = Path(out_dir) / _zip_name()
    assert zip_path.is_file(), f"builder did not write {zip_path}:\n{proc.stdout}"
    return zip_path


@pytest.fixture(scope="session")
def blender_user_dir():
    """The session's private BLENDER_USER_RESOURCES directory."""
    return Path(_USER_DIR)


@pytest.fixture(scope="session")
def extension_zip(tmp_path_factory):
    """The linux-x64 extension zip: dist/'s if newer than every packaged file,
    otherwise freshly built into a private directory (dist/ may be shared with
    other concurrent runs, so it is not rewritten here)."""
    zip_path = REPO_ROOT / "dist" / _zip_name()
    if zip_path.is_file() and zip_path.stat().st_mtime >= _newest_source_mtime():
        return zip_path
    return build_extension(tmp_path_factory.mktemp("dist"))


def _addon_enabled(module_name):
    import addon_utils
    import bpy

    return (module_name in bpy.context.preferences.addons
            and addon_utils.check(module_name)[1])


def _enable_addon(module_name):
    import addon_utils

    errors = []
    addon_utils.enable(module_name, default_set=True,
                       handle_error=lambda ex: errors.append(ex))
    if errors:
        raise errors[0]


@pytest.fixture(scope="session")
def installed_addon(extension_zip):
    """Install the built zip into the session's user_default repository the
    way a user would (Preferences > Get Extensions > Install from Disk) and
    yield the add-on's module name, ``bl_ext.user_default.artdef``."""
    import bpy

    result = bpy.ops.extensions.package_install_files(
        filepath=str(extension_zip), repo="user_default", enable_on_install=True)
    # The operator reports FINISHED even when nothing was installed: check.
    assert result == {"FINISHED"}, result
    if not _addon_enabled(ADDON_MODULE):
        _enable_addon(ADDON_MODULE)
    assert _addon_enabled(ADDON_MODULE), f"{ADDON_MODULE} is not enabled after install"
    yield ADDON_MODULE


@pytest.fixture
def clean_scene(installed_addon):
    """A fresh, empty scene with the add-on still registered."""
    import bpy

    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
    if not _addon_enabled(installed_addon):
        _enable_addon(installed_addon)
    assert _addon_enabled(installed_addon)
    yield bpy.context.scene


@pytest.fixture(scope="session")
def pkg(installed_addon):
    """Modules of the installed extension (the operator tests' references)."""
    class P:
        scan = importlib.import_module(installed_addon + ".artdef_addon.scan")
        files = importlib.import_module(installed_addon + ".artdef_addon.files")
        samples = importlib.import_module(installed_addon + ".artdef_addon.samples")
        model = importlib.import_module(installed_addon + ".artdef_addon.model")
        residuals = importlib.import_module(installed_addon + ".artdef_addon.residuals")
        result = importlib.import_module(installed_addon + ".artdef_addon.result")
        ops = importlib.import_module(installed_addon + ".operators.ops")
        api = importlib.import_module(installed_addon + ".artdef_addon.api")
        cost = importlib.import_module(installed_addon + ".artdef_addon.cost")
        io = importlib.import_module(installed_addon + ".operators.io")
        rig = importlib.import_module(installed_addon + ".operators.rig")
        drivers = importlib.import_module(installed_addon + ".artdef_addon.drivers")
    return P


@pytest.fixture(scope="session")
def sample_files(pkg, tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    out = {}
    for name in ("rod", "branching", "greens_rod"):
        path = d / f"{name}.npz"
        pkg.files.write_scan(path, pkg.samples.make(name))
        out[name] = str(path)
    return out


_TESTS = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config, items):
    """Mark each test by its layer (markers registered in pytest.ini): ``core`` under tests/core
    (the numerical core, no Blender, minutes at most) and tests/core_heavy (also ``heavy``: real
    rigs and link-count sweeps), ``blender`` under tests/blender."""
    for item in items:
        parts = Path(str(item.path)).resolve().relative_to(_TESTS).parts
        layer = parts[0] if parts else ""
        if layer in ("core", "core_heavy"):
            item.add_marker(pytest.mark.core)
        if layer == "core_heavy":
            item.add_marker(pytest.mark.heavy)
        if layer == "blender":
            item.add_marker(pytest.mark.blender)


# --------------------------------------------------------------------------
# process exit
# --------------------------------------------------------------------------
# The bpy 4.5 module can deadlock in its C++ static destructors at interpreter
# exit after a glTF import/export (operators/compat.py, "Process exit"): the
# test process would then never end.  Once pytest has printed everything
# (pytest_unconfigure is its last hook), run the Python exit handlers and leave
# with pytest's exit status, skipping the C-level teardown.

@pytest.fixture
def interrupt_at():
    """``run(cmd, marker, cwd, sig=SIGINT) -> (exit code, stderr)``: run ``cmd`` with the repository
    on PYTHONPATH and send ``sig`` as soon as a line of its stdout contains ``marker`` (Ctrl-C tests;
    SIGTERM for ``kill`` and ``timeout``)."""
    import signal

    def run(cmd, marker, cwd, sig=signal.SIGINT):
        env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), PYTHONUNBUFFERED="1")
        p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=cwd)
        seen = []
        for line in p.stdout:
            seen.append(line)
            if marker in line:
                p.send_signal(sig)
                break
        try:
            _, err = p.communicate(timeout=600)
        finally:
            p.kill()
        assert any(marker in s for s in seen), (seen, err)
        return p.returncode, err
    return run


_EXIT_STATUS = [0]


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS[0] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if sys.modules.get("bpy") is None:
        return
    import atexit
    from artdef_addon.cli import remove_blender_tempdir
    atexit._run_exitfuncs()
    remove_blender_tempdir()      # Blender's session folder: its teardown is skipped below
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(_EXIT_STATUS[0])
