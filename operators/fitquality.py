# SPDX-License-Identifier: GPL-3.0-or-later
"""Fit quality figures for the UI, from a FitResult (numpy only, no ``bpy``).

* :func:`vertex_residual` — per vertex, the RMS over fields of
  ``|x_field − x_art|``: how far the articulated motion alone (bones, no
  residual shape keys) lands from each measured pose;
* :func:`link_stats` — per link its parent, joint error, rigid residual (RMS
  over fields of ``FitResult.link_residuals``) and triangle count;
* :func:`ramp` — blue → cyan → green → yellow → red colours for values in [0, 1].
"""

import numpy as np

from ..artdef_addon import model as _model

#: sRGB stops of the residual colour ramp, at 0, 1/4, 1/2, 3/4, 1.
RAMP = np.array([
    (0.10, 0.25, 0.95),
    (0.10, 0.80, 0.95),
    (0.30, 0.85, 0.30),
    (0.98, 0.85, 0.15),
    (0.90, 0.12, 0.10),
])


def vertex_residual(result, scan, field_idx=None):
    """(N,) RMS over the model's fields of |rest + field − articulated position|.

    ``field_idx`` lists the scan fields the model was fitted to (a pseudo
    model: its load point's three columns); default all fields.
    """
    rest = np.asarray(scan.vertices, dtype=np.float64)
    fields = scan.fields()
    if field_idx is not None:
        fields = fields[np.asarray(field_idx)]
    params = result.params
    if len(params) != len(fields):
        raise ValueError(f"the model has {len(params)} poses but {len(fields)} fields were given")
    zeros = np.zeros(np.asarray(result.residual).shape[0])
    acc = np.zeros(len(rest))
    for p in range(len(fields)):
        x_art = _model.deform(result, rest, params[p], zeros)
        d = x_art - rest - fields[p]
        acc += np.einsum("nd,nd->n", d, d)
    return np.sqrt(acc / max(len(fields), 1))


def link_stats(result):
    """Per link: dict(link, parent, grounded, has_joint, joint_error, rigid_residual, triangles)."""
    res = np.asarray(result.link_residuals, dtype=np.float64)
    rigid = np.sqrt(np.mean(res ** 2, axis=0)) if res.size else np.zeros(result.n_links)
    labels = np.asarray(result.face_labels)
    out = []
    for l in range(result.n_links):
        err = float(result.joint_errors[l])
        out.append(dict(link=l, parent=int(result.parents[l]), grounded=bool(result.grounded[l]),
                        has_joint=bool(np.isfinite(err)), joint_error=err if np.isfinite(err) else 0.0,
                        rigid_residual=float(rigid[l]),
                        triangles=int(np.count_nonzero(labels == l))))
    return out


def ramp(t):
    """(n, 4) sRGB colours for ``t`` in [0, 1] (clipped): blue → red."""
    t = np.clip(np.nan_to_num(np.asarray(t, dtype=np.float64)), 0.0, 1.0)
    x = t * (len(RAMP) - 1)
    i = np.minimum(x.astype(np.int64), len(RAMP) - 2)
    f = (x - i)[:, None]
    out = np.ones((len(t), 4))
    out[:, :3] = RAMP[i] * (1 - f) + RAMP[i + 1] * f
    return out
