"""Blender driver expressions of a Green's-scan rig, as text (no ``bpy``: testable without Blender).

A load empty k's location drives, through κ (paper §7.2), the link helper bones linearly and the
residual shape keys: a first-order key through the strain-hardening map and a probe-exactness
bump key per field (:func:`artdef_addon.model.greens_keys`). Blender keeps at most 255 characters of a
driver's expression and evaluates "simple expressions" without Python; everything written here is
one. A linear sum too long for one expression is cut into partial sums (:func:`linear_chunks`),
each its own driver, added by a SUM driver.

Variables: ``x<k>``, ``y<k>``, ``z<k>`` are load k's location components; flat load component c
is axis ``c % 3`` of load ``c // 3`` (:func:`load_var`).
"""
from __future__ import annotations

import math

from . import model as _model

#: Longest driver expression written (Blender keeps 255 characters). Longer sums are split into
#: partial sums held in custom properties of the armature.
MAX_EXPRESSION = 250
AXES = "xyz"


def number(x) -> str:
    """``x`` as it appears in an expression (9 significant digits)."""
    return "%.9g" % float(x)


def load_var(c: int) -> str:
    """The variable name of flat load component ``c`` (axis ``c % 3`` of load ``c // 3``)."""
    return f"{AXES[c % 3]}{c // 3}"


def linear_terms(coeffs, var_names) -> list:
    """``["<c>*<v>", …]`` for the non-zero coefficients."""
    return [f"{number(c)}*{v}" for c, v in zip(coeffs, var_names) if c != 0.0]


def join(terms) -> str:
    """The sum of ``terms`` as one expression ("0" for none)."""
    if not terms:
        return "0"
    return "+".join(terms).replace("+-", "-")


def linear_chunks(coeffs, max_length: int | None = None) -> list:
    """The flat load components of Σ_c coeffs[c]·load[c] in groups whose expressions fit in
    ``max_length`` characters (default :data:`MAX_EXPRESSION`): a list of lists of component
    indices, zero coefficients left out; one (possibly empty) group when the sum fits."""
    limit = MAX_EXPRESSION if max_length is None else max_length
    chunks, current, length = [], [], 0
    for c in range(len(coeffs)):
        if coeffs[c] == 0.0:
            continue
        term = len(number(coeffs[c])) + len(load_var(c)) + 2
        if current and length + term > limit:
            chunks.append(current)
            current, length = [], 0
        current.append(c)
        length += term
    if current or not chunks:
        chunks.append(current)
    return chunks


def linear_expression(coeffs, components) -> str:
    """The expression of Σ over ``components`` of coeffs[c]·load[c]."""
    return join(linear_terms([coeffs[c] for c in components], [load_var(c) for c in components]))


def shape_value_expression(k, d, probe_load, p_max):
    """Simple expression of first-order shape key value c = 3k+d from load k (x<k>, y<k>, z<k>):
    h(p_k)[d] / (p̂ σ) / √(1 + (s/S)²), h the strain-hardening map and σ its slope at zero (identity
    and 1 when off), s = |p_k|/p̂, S the keys' saturation (:func:`artdef_addon.model.greens_key_values`)."""
    x, y, z = (f"{a}{k}" for a in AXES)
    v = f"{AXES[d]}{k}"
    n2 = f"({x}*{x}+{y}*{y}+{z}*{z})"
    sat = f"/sqrt(1+{number(1.0 / (_model.KEY_SATURATION * probe_load) ** 2)}*{n2})"
    if p_max is None:
        return f"{number(1.0 / probe_load)}*{v}{sat}"
    # s~ = p_max (1 - q^s), q = (p_max-1)/p_max, s = |p|/p̂  ->  q^s = exp(|p| ln(q)/p̂)
    rate = math.log((p_max - 1.0) / p_max) / probe_load
    n = f"sqrt({n2})"
    return (f"{number(p_max / _model.hardening_slope(p_max))}*(1-exp({number(rate)}*{n}))*{v}/max({n},1e-30)"
            + sat)


def bump_value_expression(k, d, probe_load):
    """Simple expression of bump shape key value c = 3k+d from load k: (p_kd/p̂)² s⁴ e^(6(1−s)),
    s = |p_k|/p̂ (:data:`artdef_addon.model.BUMP_POWER` = 6; :func:`artdef_addon.model.greens_key_values`)."""
    x, y, z = (f"{a}{k}" for a in AXES)
    v = f"{AXES[d]}{k}"
    n2 = f"({x}*{x}+{y}*{y}+{z}*{z})"
    i2 = number(1.0 / probe_load ** 2)
    power = _model.BUMP_POWER
    return (f"{v}*{v}*{i2}*" + "*".join([f"{n2}*{i2}"] * ((power - 2) // 2))
            + f"*exp({number(power)}-{number(power / probe_load)}*sqrt({n2}))")


#: variable names of a load's turn in :func:`felt_expression`
TURN_VARS = ("wx", "wy", "wz")


def felt_expression(k, d) -> str:
    """Simple expression of component d of load k as its link feels it (:func:`artdef_addon.model.dead_loads`):
    the load (x<k>, y<k>, z<k>) turned back by the link's turn w (wx, wy, wz), Rodrigues' formula
    cos θ f − sin θ/θ w × f + (1 − cos θ)/θ² w (w·f), θ = |w| (:func:`artdef_addon.model.rotate_vectors`
    of −w)."""
    f = [f"{a}{k}" for a in AXES]
    w = TURN_VARS
    t = "sqrt(wx*wx+wy*wy+wz*wz)"
    i, j = (d + 1) % 3, (d + 2) % 3
    cross = f"({w[i]}*{f[j]}-{w[j]}*{f[i]})"
    dot = f"({w[0]}*{f[0]}+{w[1]}*{f[1]}+{w[2]}*{f[2]})"
    return (f"cos({t})*{f[d]}-sin({t})/max({t},1e-30)*{cross}"
            f"+(1-cos({t}))/max(wx*wx+wy*wy+wz*wz,1e-60)*{w[d]}*{dot}")
