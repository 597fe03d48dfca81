"""The names of the fit's modules under their earlier home (kept so that imports keep working).

The fit lives in :mod:`.result` (:class:`FitResult`, its file), :mod:`.segmenter`
(:class:`Segmenter`), :mod:`.stages` (:class:`FitState`, the stages, :func:`run_stages`) and
:mod:`.pipeline` (:func:`fit`, :func:`fit_until`); new code imports from those. Any other name
of those modules is looked up there when asked for.
"""
from . import pipeline as _pipeline, result as _result_module, segmenter as _segmenter, stages as _stages
from .pipeline import fit, fit_until  # noqa: F401
from .result import (FitCancelled, FitResult, load_result, report, result_arrays, result_from_arrays,  # noqa: F401
                     save_result)
from .segmenter import SEGMENT_FIELDS, STRATEGIES, Segmenter, select_fields  # noqa: F401
from .stages import (EXACT_JOINT, NEAR_BLOCK, RESIDUAL_BLOCK_BYTES, STAGES, FitState,  # noqa: F401
                     joint_of, link_motions, new_state, relabelled, run_stages, stage_bones, stage_joints,
                     stage_motions, stage_pose, stage_relabel, stage_residuals, stage_segment, stage_skin,
                     stage_split, to_result)


def __getattr__(name):
    for module in (_stages, _segmenter, _result_module, _pipeline):
        if hasattr(module, name):
            return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
