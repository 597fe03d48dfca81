# SPDX-License-Identifier: GPL-3.0-or-later
"""The mesh attributes a fit writes: link colours (face corners) and the articulation residual.

* ``artdef_links`` (BYTE_COLOR, CORNER): each face in its link's colour, the active colour;
* ``artdef_residual`` (FLOAT, POINT): the per-vertex articulation residual, and its colours
  ``artdef_residual_color`` (FLOAT_COLOR, POINT, blue = 0 → red = largest).
"""

import colorsys

import numpy as np

from .names import COLOR_ATTR, RESIDUAL_ATTR, RESIDUAL_COLOR_ATTR


# Twelve clearly different sRGB colours for the first links, then golden-ratio hues.
_PALETTE = (
    (0.90, 0.45, 0.20), (0.25, 0.50, 0.90), (0.45, 0.78, 0.30), (0.85, 0.25, 0.55),
    (0.95, 0.82, 0.25), (0.35, 0.80, 0.85), (0.55, 0.35, 0.80), (0.80, 0.22, 0.22),
    (0.60, 0.48, 0.32), (0.20, 0.62, 0.55), (0.97, 0.62, 0.78), (0.70, 0.88, 0.55),
)


def link_colours(n):
    """(n, 4) sRGB colours, well separated, deterministic."""
    out = np.ones((n, 4))
    for i in range(n):
        if i < len(_PALETTE):
            out[i, :3] = _PALETTE[i]
        else:
            h = (0.05 + i * 0.618033988749895) % 1.0
            out[i, :3] = colorsys.hsv_to_rgb(h, 0.5 + 0.25 * (i % 2), 0.95 - 0.15 * ((i // 2) % 2))
    return out


def write_link_colours(mesh, tri_labels, tri_polygons):
    """Colour polygons by link in the CORNER byte colour attribute ``artdef_links``."""
    n_poly = len(mesh.polygons)
    poly_label = np.zeros(n_poly, dtype=np.int64)
    poly_label[np.asarray(tri_polygons)] = np.asarray(tri_labels)
    totals = np.empty(n_poly, dtype=np.int32)
    mesh.polygons.foreach_get("loop_total", totals)
    corner_label = np.repeat(poly_label, totals)
    colours = link_colours(int(poly_label.max()) + 1 if n_poly else 1)[corner_label]
    old = mesh.color_attributes.get(COLOR_ATTR)
    if old is not None:
        mesh.color_attributes.remove(old)
    attr = mesh.color_attributes.new(COLOR_ATTR, 'BYTE_COLOR', 'CORNER')
    attr.data.foreach_set("color_srgb", np.ascontiguousarray(colours, dtype=np.float32).ravel())
    set_active_colour(mesh, COLOR_ATTR)
    return mesh.color_attributes.get(COLOR_ATTR)


def remove_link_colours(mesh):
    attr = mesh.color_attributes.get(COLOR_ATTR)
    if attr is not None:
        mesh.color_attributes.remove(attr)


def set_active_colour(mesh, name):
    """Make colour attribute ``name`` the active and the rendered one."""
    attrs = mesh.color_attributes
    attr = attrs.get(name)
    if attr is None:
        return
    attrs.active_color = attr
    for i, a in enumerate(attrs):
        if a.name == name:
            attrs.render_color_index = i


def write_residual(mesh, values, scale):
    """Per-vertex residual magnitude as FLOAT ``artdef_residual`` and as colours
    ``artdef_residual_color`` (blue at 0 → red at ``scale``).  The active colour
    attribute is left as it was (the link colours after a fit)."""
    from .fitquality import ramp
    values = np.ascontiguousarray(values, dtype=np.float32)
    active = mesh.color_attributes.active_color
    active_name = active.name if active is not None else None
    remove_residual(mesh)
    attr = mesh.attributes.new(RESIDUAL_ATTR, 'FLOAT', 'POINT')
    attr.data.foreach_set("value", values)
    colours = ramp(values / scale if scale > 0 else np.zeros(len(values)))
    col = mesh.color_attributes.new(RESIDUAL_COLOR_ATTR, 'FLOAT_COLOR', 'POINT')
    col.data.foreach_set("color_srgb", np.ascontiguousarray(colours, dtype=np.float32).ravel())
    if active_name is not None:
        set_active_colour(mesh, active_name)


def remove_residual(mesh):
    for coll, name in ((mesh.color_attributes, RESIDUAL_COLOR_ATTR), (mesh.attributes, RESIDUAL_ATTR)):
        attr = coll.get(name)
        if attr is not None:
            coll.remove(attr)

