# SPDX-License-Identifier: GPL-3.0-or-later
"""What the add-on keeps between operator calls (in memory only, not saved in the .blend)."""

from ..artdef_addon import api as _api

#: Extra cancel checks consulted by every fit's progress callback:
#: ``hook(stage, fraction) -> bool`` (True cancels).  For scripts and tests;
#: the interactive path cancels with Esc.
PROGRESS_HOOKS = []

#: Last FitResult per mesh object name (the model behind the rig; for
#: scripting and tests — not saved in the .blend).
LAST_RESULTS = {}


def last_result(obj):
    return LAST_RESULTS.get(obj.name)


def _forget():
    """What the add-on keeps between fits: the core's cached segmenters and the last results."""
    _api.clear_cache()
    LAST_RESULTS.clear()
