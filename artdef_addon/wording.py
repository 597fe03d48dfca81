"""Plain words about a fit for people, shared by the panel and the command line (pure Python)."""


#: why a mesh sequence's face is left out of the Blender mesh (Import Mesh Sequence's report and the
#: command line's note)
DROPPED_FACES = "they repeat a vertex or another face, which a Blender mesh cannot hold"


def _percent(e):
    """A percentage in words: two significant digits below 10 %, whole numbers above."""
    return f"{e:.2g}%" if e < 10 else f"{e:.0f}%"


def plain_link_reason(links, errors, fitted=None):
    """One sentence saying why Auto Links chose ``links``.

    ``errors``: the link-count search's quick articulation error (percent of the fields' size)
    with k = 1, 2, ... links (the re-cut tree's curve, :mod:`linkcount`; NaN where the search did
    not read the count); ``fitted``: the chosen fit's own error, said instead of the curve's where
    given (the curve is a quick segmentation's, well above the fit's on a blended skin, so only its
    ratios are said). "" when there is nothing to say.
    """
    errors = [float(e) for e in (errors or [])]
    if not errors or links < 1:
        return ""
    chosen = errors[min(links, len(errors)) - 1]
    best = min((e for e in errors if e == e), default=chosen)   # counts the search skipped are NaN
    left = chosen if fitted is None or not fitted >= 0 else float(fitted)
    one = "all of it" if errors[0] >= 99.5 else _percent(errors[0])
    more = ""
    if len(errors) > links and best < chosen and chosen > 0:
        more = f"; even {len(errors)} would lower that by only {100 * (1 - best / chosen):.0f}%"
    return (f"{links} links leave {_percent(left)} of the motion unexplained (one bone leaves {one}){more}, "
            f"so more bones would mostly add clutter.")


def error_curve_lines(errors, links):
    """The error curve as short text lines: ``k links  e%`` (the chosen count marked; ``—`` where
    the search did not compute the count)."""
    return [(f"{k:>2} links  {e:6.2f}%" if e == e else f"{k:>2} links       —") + ("  <" if k == links else "")
            for k, e in enumerate((float(x) for x in errors or []), start=1)]
