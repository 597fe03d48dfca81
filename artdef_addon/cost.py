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


def estimate(triangles: int, fields: int, vertices: int, strategy: str = "summed",
             budget: float = DEFAULT_BUDGET, units: int | None = None) -> Estimate:
    """Estimate a fit; ``reduced`` says whether the full method would exceed ``budget`` bytes."""
    full = full_memory(triangles, fields, vertices)
    reduced = full > budget
    u = triangles if not reduced else (units or min(triangles, reduced_units(budget, fields)))
    pairs = u * (u - 1) / 2
    linkages = 1 if strategy == "summed" else fields
    seconds = 2 * pairs * fields / PAIRS_PER_SECOND + linkages * pairs * LINKAGE_SECONDS_PER_ENTRY
    if reduced:
        seconds += triangles * fields * 2.5e-6  # streamed features and neighbour distances
        mem = 2 * 8.0 * pairs + FEATURE_BYTES * (u * fields + triangles) + 8.0 * 3 * vertices * fields * 2
    else:
        mem = full
    return Estimate(triangles, fields, u, mem, seconds, reduced)


#: most patch representatives the reduced method uses (time grows with their square × fields)
MAX_UNITS = 1000
#: fewest patch representatives (below this the patches get too coarse for thin links)
MIN_UNITS = 500
#: U²·P budget of the reduced method's pairwise stage: with many fields it uses fewer patches
PAIR_FIELD_WORK = 2.0e7


def reduced_units(budget: float = DEFAULT_BUDGET, fields: int | None = None) -> int:
    """How many patch representatives the reduced method uses: what a quarter of the budget
    holds as a condensed matrix, at most :data:`MAX_UNITS`, and with ``fields`` at most
    √(PAIR_FIELD_WORK / fields) (so 1,000 up to 20 fields, 632 at 50, 500 from 80), never
    fewer than :data:`MIN_UNITS`."""
    u = min(MAX_UNITS, (budget / 4 / 8 * 2) ** 0.5)
    if fields:
        u = min(u, (PAIR_FIELD_WORK / fields) ** 0.5)
    return int(max(MIN_UNITS, u))
