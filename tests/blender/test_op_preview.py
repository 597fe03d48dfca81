"""The Preview Links operator.

Run headless (bpy module) through the installed extension.

Everything goes through ``bpy.ops.artdef.*`` of the extension installed from the built zip
(fixtures ``installed_addon``, ``clean_scene``, ``pkg`` and ``sample_files`` in tests/conftest.py);
the core used for reference numbers is the installed copy too.
"""

import importlib
import os

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from ophelpers import import_scan


def test_preview_segments_in_the_worker_process_and_cancels(clean_scene, pkg, sample_files):
    """Preview Links runs its first clustering in the worker process: the worker gives the same
    links as the core in this process, and a cancel leaves no kept clustering and no colours."""
    obj = import_scan(sample_files["branching"])
    pkg.ops.worker.forget()
    job = pkg.ops._preview_job(obj, 11)
    assert not job.cached
    job.start().wait()
    assert job.error is None and job.labels is not None
    assert job.pid is not None and job.pid != os.getpid()       # computed in the worker process
    core = pkg.scan.__name__.rsplit(".", 1)[0]
    ref = importlib.import_module(core + ".segmenter").Segmenter(pkg.io.read_scan(obj).scan).labels(11)
    assert len(np.unique(job.labels)) == 11 and np.array_equal(job.labels, ref)
    stages = []

    def hook(stage, fraction):
        stages.append(stage)
        return True  # cancel at the first report

    pkg.ops.worker.forget()  # the first preview kept its clustering: cancel a fresh one
    pkg.ops.PROGRESS_HOOKS.append(hook)
    try:
        job = pkg.ops._preview_job(obj, 11)
        job.start().wait()
    finally:
        pkg.ops.PROGRESS_HOOKS.remove(hook)
    assert stages and isinstance(job.error, importlib.import_module(core + ".result").FitCancelled)
    assert pkg.ops.cached_segmentation(obj) is None
    assert "artdef_links" not in obj.data.color_attributes


def test_preview_links_colours_faces_from_cached_clustering(clean_scene, pkg, sample_files):
    obj = import_scan(sample_files["branching"])
    pkg.ops.worker.forget()
    assert bpy.ops.artdef.preview_links(links=11) == {'FINISHED'}
    seg = pkg.ops.cached_segmentation(obj)
    assert seg is not None
    attr = obj.data.color_attributes["artdef_links"]
    assert attr.domain == 'CORNER' and attr.data_type == 'BYTE_COLOR'
    assert obj.data.color_attributes.active_color.name == "artdef_links"

    def n_colours():
        c = np.empty(4 * len(attr.data), dtype=np.float32)
        obj.data.color_attributes["artdef_links"].data.foreach_get("color_srgb", c)
        return len(np.unique(c.reshape(-1, 4).round(3), axis=0))

    assert n_colours() == 11
    assert bpy.ops.artdef.preview_links(links=5) == {'FINISHED'}
    attr = obj.data.color_attributes["artdef_links"]
    assert n_colours() == 5
    assert pkg.ops.cached_segmentation(obj) == seg  # distances not recomputed
    # the fit reuses the cached clustering too, and colours by its links
    assert bpy.ops.artdef.fit(links=11) == {'FINISHED'}
    assert pkg.ops.cached_segmentation(obj) == seg
    attr = obj.data.color_attributes["artdef_links"]
    assert n_colours() == 11
