# SPDX-License-Identifier: GPL-3.0-or-later
"""The names ArtDef gives to what it makes in a scene (Clear Rig and a re-fit find them by these)."""

GROUP_FMT = "artdef_link_{:02d}"
HELPER_FMT = GROUP_FMT + "_load"   # Green's scans: the load-driven helper bone of a link
HELPER_COLLECTION = "ArtDef Load Helpers"
LOAD_CONSTRAINT = "ArtDef Load"
KEY_PREFIX = "artdef_field_"
LOAD_FMT = "artdef_load_{}"
MODIFIER_NAME = "ArtDef Armature"
COLOR_ATTR = "artdef_links"
RESIDUAL_ATTR = "artdef_residual"
RESIDUAL_COLOR_ATTR = "artdef_residual_color"
#: Prefix of the temporary names of the previous rig's pieces while a new rig is built
#: (names starting with "." are hidden from most of Blender's lists).
STASH_PREFIX = ".artdef_prev_"
#: a Green's rig's posing version, stored on its armature (``RIG_VERSION_PROP``): 4 = joint turns
#: from rotational springs balanced against the dead loads' torques (artdef_addon.springs) with one
#: first-order residual key a field (model.greens_keys); an older Green's rig (3: turns linear in the
#: loads its links feel, with probe-exactness bump keys; 2: linear in the empties' loads; none: the
#: probe residual scaled linearly) keeps posing as it did and is told to be refitted
#: (:func:`.rig.stale_greens_rig`)
RIG_VERSION = 4
RIG_VERSION_PROP = "artdef_rig_version"
