"""Blender driver expressions of a Green's-scan rig, as text (no ``bpy``: testable without Blender).

A load empty k's location drives the joints' spring turns (:mod:`artdef_addon.springs`: chained
rotations of felt loads and lever arms, torques, damped steps), the link helper bones from them, and
the residual shape keys, one a field, through the strain-hardening map
(:func:`artdef_addon.model.greens_keys`). Blender keeps at most 255 characters of a
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


#: variable names of a rotation vector and of the vector it turns in :func:`rotate_expression`
TURN_VARS = ("a", "b", "c")
VECTOR_VARS = ("x", "y", "z")


def rotate_expression(d, sign=1, offset=0.0) -> str:
    """Simple expression of component d of offset + the vector (x, y, z) turned by the rotation vector
    ±(a, b, c) (``sign``): Rodrigues' cos θ v ± sin θ/θ w × v + (1 − cos θ)/θ² w (w·v), θ = |w|
    (:func:`artdef_addon.springs.rotate`)."""
    w, v = TURN_VARS, VECTOR_VARS
    n2 = "(a*a+b*b+c*c)"
    t = f"sqrt({n2})"
    i, j = (d + 1) % 3, (d + 2) % 3
    cross = f"({w[i]}*{v[j]}-{w[j]}*{v[i]})"
    dot = "(a*x+b*y+c*z)"
    head = f"{number(offset)}+" if offset != 0.0 else ""
    return (f"{head}cos({t})*{v[d]}{'+' if sign > 0 else '-'}sin({t})/max({t},1e-30)*{cross}"
            f"+(1-cos({t}))/max({n2},1e-60)*{w[d]}*{dot}")


def cross_expression(d) -> str:
    """Simple expression of component d of the cross product of (x, y, z) and (a, b, c)."""
    i, j = (d + 1) % 3, (d + 2) % 3
    v, w = VECTOR_VARS, TURN_VARS
    return f"{v[i]}*{w[j]}-{v[j]}*{w[i]}"


def quaternion_expression(i, frame) -> str:
    """Simple expression of quaternion component i (w, x, y, z) of the bone-local rotation of the turn
    (a, b, c) in rest coordinates: cos(θ/2) and sin(θ/2)/θ · (Bᵀ ω)_(i−1), B = ``frame`` (3, 3)."""
    t = "sqrt(a*a+b*b+c*c)"
    if i == 0:
        return f"cos(0.5*{t})"
    col = [frame[r][i - 1] for r in range(3)]
    return f"sin(0.5*{t})/max({t},1e-30)*({join(linear_terms(col, TURN_VARS))})"


def spring_step_expression(damping, compliance_row) -> str:
    """Simple expression of a turn component after one damped step: (1 − d) p + d (C_row · (t0, t1, t2)
    + e), p the previous turn, t the torque in the parent's frame, e the linear remainder E f."""
    terms = linear_terms(compliance_row, ("t0", "t1", "t2")) + ["e"]
    return f"{number(1.0 - damping)}*p+{number(damping)}*({join(terms)})"
