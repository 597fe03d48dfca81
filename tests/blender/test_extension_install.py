"""The built extension zip: contents, install through Blender's own operator,
enable/disable cycles, and the bundled scipy wheel."""

import os
import subprocess
import sys
import textwrap
import tomllib
import zipfile

from conftest import BUNDLED_SCIPY, PYTHON_TAG, REPO_ROOT

#: The scipy this Python's Blender installs from the zip.
SCIPY_VERSION = BUNDLED_SCIPY.get(sys.version_info[:2], "none for this Python")
#: Per platform zip: the platform tag of its cp311 and of its cp313 wheel.
PLATFORM_WHEEL_TAGS = {
    "linux_x64": ("manylinux_2_17_x86_64", "manylinux_2_17_x86_64"),
    "windows_x64": ("win_amd64", "win_amd64"),
    "macos_arm64": ("macosx_12_0_arm64", "macosx_12_0_arm64"),
    "macos_x64": ("macosx_10_13_x86_64", "macosx_10_14_x86_64"),
}


def _names(zip_path):
    with zipfile.ZipFile(zip_path) as zf:
        return zf.namelist()


def test_zip_contains_the_package_and_only_the_package(extension_zip):
    names = _names(extension_zip)
    tops = {n.split("/", 1)[0] for n in names}
    for required in ("__init__.py", "blender_manifest.toml", "artdef_addon",
                     "operators", "panels", "wheels"):
        assert required in tops, f"{required} missing from {extension_zip.name}: {sorted(tops)}"
    for excluded in ("tests", "benchmarks", "scripts", ".venv", ".git", ".ci", ".tools",
                     "dist", "out", "node_modules", "docs", "Makefile", "pytest.ini",
                     "requirements-dev.txt", ".gitignore"):
        assert excluded not in tops, f"{excluded} must not be packaged"
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]
    wheels = sorted(n for n in names if n.endswith(".whl"))
    assert wheels == [
        "wheels/scipy-1.15.3-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
        "wheels/scipy-1.16.3-cp313-cp313-manylinux2014_x86_64.manylinux_2_17_x86_64.whl"], wheels
    assert not [n for n in names if "numpy" in n.lower()], "numpy must never be bundled"


def test_each_platform_zip_has_only_its_own_wheels(extension_zip):
    """One cp311 (Blender 4.5 LTS, 5.0) and one cp313 (5.1+) scipy wheel per
    platform zip, both for that platform only."""
    for platform, (tag311, tag313) in PLATFORM_WHEEL_TAGS.items():
        z = extension_zip.with_name(extension_zip.name.replace("linux_x64", platform))
        assert z.is_file(), f"{z.name} was not built"
        wheels = sorted(n for n in _names(z) if n.endswith(".whl"))
        assert len(wheels) == 2, (platform, wheels)
        assert "cp311-cp311" in wheels[0] and tag311 in wheels[0], (platform, wheels)
        assert "cp313-cp313" in wheels[1] and tag313 in wheels[1], (platform, wheels)


def test_zip_manifest(extension_zip):
    with zipfile.ZipFile(extension_zip) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    assert manifest["id"] == "artdef"
    assert manifest["type"] == "add-on"
    # 4.2 LTS is out of support and its glTF exporter fails on a Green's rig
    assert manifest["blender_version_min"] == "4.5.0"
    assert len(manifest["tagline"]) <= 64 and manifest["tagline"][-1].isalnum()
    assert set(manifest["platforms"]) == {"linux-x64", "windows-x64", "macos-arm64", "macos-x64"}
    # Every listed wheel is shipped in the source tree's wheels/ (build_wheels.sh).
    for w in manifest["wheels"]:
        assert (REPO_ROOT / w).is_file(), w


def test_installed_addon_is_enabled(installed_addon, blender_user_dir):
    import addon_utils
    import bpy

    assert installed_addon == "bl_ext.user_default.artdef"
    assert installed_addon in bpy.context.preferences.addons
    assert addon_utils.check(installed_addon) == (True, True)
    mod = sys.modules[installed_addon]
    # The installed copy, not the source tree.
    assert os.path.realpath(mod.__file__).startswith(os.path.realpath(blender_user_dir))


def test_operators_are_registered(installed_addon):
    import bpy

    # hasattr() is always True on bpy.ops sub-modules; dir() lists only the
    # operators that are really registered.
    registered = dir(bpy.ops.artdef)
    assert "import_scan" in registered, f"bpy.ops.artdef.import_scan missing: {registered}"
    assert "fit" in registered, f"bpy.ops.artdef.fit missing: {registered}"


def test_register_unregister_twice(installed_addon):
    import addon_utils
    import bpy

    errors = []
    for _ in range(2):
        addon_utils.disable(installed_addon, default_set=True, handle_error=errors.append)
        assert not addon_utils.check(installed_addon)[1]
        assert installed_addon not in bpy.context.preferences.addons
        left = [op for op in dir(bpy.ops.artdef) if not op.startswith("_")]
        assert not left, f"operators still registered after disable: {left}"
        addon_utils.enable(installed_addon, default_set=True, handle_error=errors.append)
        assert addon_utils.check(installed_addon)[1]
        assert "fit" in dir(bpy.ops.artdef)
    assert not errors, errors
    # The package's own register()/unregister() pair, called directly, twice.
    mod = sys.modules[installed_addon]
    for _ in range(2):
        mod.unregister()
        mod.register()
    assert installed_addon in bpy.context.preferences.addons


def _extension_site_packages(user_dir):
    return user_dir / "extensions" / ".local" / "lib" / PYTHON_TAG / "site-packages"


def test_bundled_scipy_wheel_is_installed(installed_addon, blender_user_dir):
    site = _extension_site_packages(blender_user_dir)
    assert (site / "scipy" / "__init__.py").is_file(), f"no scipy under {site}"
    assert (site / f"scipy-{SCIPY_VERSION}.dist-info").is_dir(), sorted(os.listdir(site))
    assert len([d for d in os.listdir(site) if d.startswith("scipy-")]) == 1, "one scipy only"
    assert not (site / "numpy").exists(), "numpy must not be installed from the extension"


# Runs in a Python whose site-packages has everything of the venv except scipy
# (a directory of symlinks), like Blender itself, which ships no scipy.
_NO_SCIPY_PROBE = textwrap.dedent("""
    import os, sys, tempfile
    site = next(p for p in sys.path if p.endswith("site-packages"))
    shadow = tempfile.mkdtemp()
    for name in os.listdir(site):
        if not name.startswith("scipy"):
            os.symlink(os.path.join(site, name), os.path.join(shadow, name))
    sys.path[sys.path.index(site)] = shadow
    try:
        import scipy
        raise SystemExit("scipy still importable without the extension: " + scipy.__file__)
    except ImportError:
        pass
    import bpy, addon_utils
    addon_utils.enable(sys.argv[1], default_set=True)
    assert addon_utils.check(sys.argv[1])[1], "add-on did not enable"
    import scipy, scipy.sparse.linalg, scipy.optimize
    print(scipy.__version__)
    print(scipy.__file__)
""")


def test_bundled_scipy_is_what_the_addon_imports(installed_addon, blender_user_dir):
    proc = subprocess.run(
        [sys.executable, "-c", _NO_SCIPY_PROBE, installed_addon],
        capture_output=True, text=True, timeout=120,
        env=dict(os.environ, BLENDER_USER_RESOURCES=str(blender_user_dir)),
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    version, path = proc.stdout.strip().splitlines()[-2:]
    assert version == SCIPY_VERSION
    assert os.path.realpath(path).startswith(
        os.path.realpath(_extension_site_packages(blender_user_dir))), path
