"""Know the cost before paying it: time and memory estimates of a fit.

The constants were measured on the project's 2-core reference machine (see
``benchmarks/bench_core.py``); they are rough by design — the point is to know whether a fit
takes seconds or hours and whether the all-pairs distance fits in memory.
"""
from __future__ import annotations

import dataclasses

#: residual-pair evaluations per second of the pairwise stage (two products + element-wise work)
PAIRS_PER_SECOND = 3.0e7
#: average-linkage seconds per condensed entry (scipy's nearest-neighbour chain)
LINKAGE_SECONDS_PER_ENTRY = 9.0e-8
#: reduced method: seconds per triangle × field of the streamed features and neighbour distances
#: (its measurement: ``benchmarks/results/core_constants.md``)
REDUCED_SECONDS_PER_TRIANGLE_FIELD = 8.0e-6
#: bytes per triangle per field of the cached per-field features
FEATURE_BYTES = 8 * 63
DEFAULT_BUDGET = 2 * 1024 ** 3


@dataclasses.dataclass
class Estimate:
    triangles: int
    fields: int
    units: int
    memory_bytes: float
    seconds: float
    reduced: bool

    def describe(self) -> str:
        how = (f"reduced method on about {self.units} patches" if self.reduced
               else f"full method on {self.triangles} triangles")
        return (f"estimate: {how}, {self.fields} fields: about {format_bytes(self.memory_bytes)} peak, "
                f"{self.seconds:.0f} s")


def format_bytes(n: float) -> str:
    """'1.9 GB', '16 MB', '512 kB'."""
    for unit, size in (("GB", 2 ** 30), ("MB", 2 ** 20), ("kB", 2 ** 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}" if unit == "GB" else f"{n / size:.0f} {unit}"
    return f"{n:.0f} B"


def full_memory(triangles: int, fields: int, vertices: int) -> float:
    """Peak bytes of the full method: condensed ε twice (linkage copies it), features, fields."""
    cond = 8.0 * triangles * (triangles - 1) / 2
    return 2 * cond + FEATURE_BYTES * triangles * fields + 8.0 * 3 * vertices * fields * 2


#: links assumed by the estimate when the count is not given (or chosen automatically)
DEFAULT_LINKS = 20
#: tracked scans: the articulation stage (the relabelling's skin decompositions, link swaps and the
#: refined skin, each round O(N·L·(P + m²)), see :mod:`skinning`): seconds per vertex × link and
#: per vertex × link × field, fitted to the shared rigged sets' stage timings
SKIN_SECONDS_PER_VERTEX_LINK = 3.0e-5
SKIN_SECONDS_PER_VERTEX_LINK_FIELD = 2.5e-6
#: the link swaps' trials (scans of at most ``swaps.SWAP_BUDGET`` vertex × fields) multiply that by
SWAP_FACTOR = 2.0
#: a ``--links auto`` search costs about this many fixed-count fits: the re-cut tree's error
#: curve, at least five whole fits upward (the count and its window) and the drop of non-bones
AUTO_FITS = 7.0
#: the search's tree error curve costs about this many fixed-count fits per count tried (a
#: segmentation and one weight solve each), and a link added to a decomposition
#: (:func:`linkcount.grow_link`) about this many
CURVE_FITS_PER_COUNT = 0.04
GROW_FITS = 0.1
#: bytes per vertex × link of the refined skin's per-vertex arrays (errors, their order, the
#: candidate masks, the link statistics), and per vertex of one block of the weight solve
SKIN_BYTES_PER_VERTEX_LINK = 48.0
SOLVE_BYTES_PER_VERTEX = 8.0 * 9 * 9 * 6


def articulation_cost(vertices: int, fields: int, links: int) -> tuple[float, float]:
    """(seconds, bytes) of a tracked scan's articulation stage (skin decompositions)."""
    from .skinning import SOLVE_BLOCK
    from .swaps import SWAP_BUDGET
    secs = vertices * links * (SKIN_SECONDS_PER_VERTEX_LINK + SKIN_SECONDS_PER_VERTEX_LINK_FIELD * fields)
    swaps = vertices * fields <= SWAP_BUDGET
    if swaps:
        secs *= SWAP_FACTOR
    solve_rows = vertices if swaps else min(vertices, SOLVE_BLOCK)   # swaps keep the whole systems
    mem = SKIN_BYTES_PER_VERTEX_LINK * vertices * (links + 1) + SOLVE_BYTES_PER_VERTEX * solve_rows
    return secs, mem


def estimate(triangles: int, fields: int, vertices: int, strategy: str = "summed",
             budget: float = DEFAULT_BUDGET, units: int | None = None, links: int | None = None,
             auto: bool = False) -> Estimate:
    """Estimate a fit; ``reduced`` says whether the full method would exceed ``budget`` bytes
    (or is chosen for speed, :func:`faster_reduced`). Tracked scans (``strategy`` "summed") add
    the articulation stage for ``links`` links (default :data:`DEFAULT_LINKS`); ``auto`` prices
    a ``--links auto`` search (:data:`AUTO_FITS` fits)."""
    full = full_memory(triangles, fields, vertices)
    reduced = full > budget or faster_reduced(triangles, fields, budget)
    u = triangles if not reduced else (units or min(triangles, reduced_units(budget, fields)))
    pairs = u * (u - 1) / 2
    linkages = 1 if strategy == "summed" else fields
    seconds = 2 * pairs * fields / PAIRS_PER_SECOND + linkages * pairs * LINKAGE_SECONDS_PER_ENTRY
    if reduced:
        seconds += triangles * fields * REDUCED_SECONDS_PER_TRIANGLE_FIELD  # streamed features, neighbour distances
        mem = 2 * 8.0 * pairs + FEATURE_BYTES * (u * fields + triangles) + 8.0 * 3 * vertices * fields * 2
    else:
        mem = full
    if strategy == "summed":
        secs, skin_mem = articulation_cost(vertices, fields, int(links or DEFAULT_LINKS))
        seconds += secs
        mem = max(mem, skin_mem + 8.0 * 3 * vertices * fields * 2 + FEATURE_BYTES * u * fields)
    if auto:
        seconds *= AUTO_FITS
    return Estimate(triangles, fields, u, mem, seconds, reduced)


#: most patch representatives the reduced method uses (time grows with their square × fields)
MAX_UNITS = 1000
#: fewest patch representatives (below this the patches get too coarse for thin links)
MIN_UNITS = 500
#: U²·P budget of the reduced method's pairwise stage: with many fields it uses fewer patches
PAIR_FIELD_WORK = 2.0e7


#: the reduced method is also used, for speed, when the scan has more than this many times the
#: patches it would use: the pairwise stage then costs (T/U)² = 4× or more than on patches, for the
#: same articulation error and ARI on the shared rigged sets (``benchmarks/results/core_constants.md``,
#: ``compare_dembones.md``)
SPEED_FACTOR = 2.0


def faster_reduced(triangles: int, fields: int, budget: float = DEFAULT_BUDGET) -> bool:
    """Whether the reduced method is chosen for speed (not memory): more than
    :data:`SPEED_FACTOR` × :func:`reduced_units` triangles. An unbounded ``budget`` (the reduced
    method switched off) never chooses it."""
    if budget == float("inf"):
        return False
    return triangles > SPEED_FACTOR * reduced_units(budget, fields)


def reduced_units(budget: float = DEFAULT_BUDGET, fields: int | None = None) -> int:
    """How many patch representatives the reduced method uses: what a quarter of the budget
    holds as a condensed matrix, at most :data:`MAX_UNITS`, and with ``fields`` at most
    √(PAIR_FIELD_WORK / fields) (so 1,000 up to 20 fields, 632 at 50, 500 from 80), never
    fewer than :data:`MIN_UNITS`."""
    u = min(MAX_UNITS, (budget / 4 / 8 * 2) ** 0.5)
    if fields:
        u = min(u, (PAIR_FIELD_WORK / fields) ** 0.5)
    return int(max(MIN_UNITS, u))
