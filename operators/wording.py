# SPDX-License-Identifier: GPL-3.0-or-later
"""Plain words for the panel (pure Python, no bpy)."""


def plain_link_reason(links, errors):
    """One sentence saying why Auto Links chose ``links``.

    errors: articulation error (percent of the fields' size) with k = 1, 2, ...
    links, as the chooser measured it; "" when there is nothing to say.
    """
    errors = [float(e) for e in (errors or [])]
    if not errors or links < 1:
        return ""
    chosen = errors[min(links, len(errors)) - 1]
    best = min((e for e in errors if e == e), default=chosen)   # counts the search skipped are NaN
    more = (f"; even {len(errors)} would only get it to {best:.1f}%"
            if len(errors) > links and best < chosen else "")
    return (f"{links} links leave {chosen:.1f}% of the motion unexplained (one bone leaves "
            f"{errors[0]:.0f}%){more}, so more bones would mostly add clutter.")


def error_curve_lines(errors, links):
    """The error curve as short text lines: ``k links  e%`` (the chosen count marked; ``—`` where
    the search did not compute the count)."""
    return [(f"{k:>2} links  {e:6.2f}%" if e == e else f"{k:>2} links       —") + ("  <" if k == links else "")
            for k, e in enumerate((float(x) for x in errors or []), start=1)]
