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
#: (``bench_core.py --scale``: 1.2-1.5e-6 on the generated scans from 17k to 1.03M triangles,
#: CesiumMan's and cheburashka's 1.6-1.7e-6; ``benchmarks/results/core_constants.md``)
REDUCED_SECONDS_PER_TRIANGLE_FIELD = 1.5e-6
#: bytes per triangle per field of the cached per-field features
FEATURE_BYTES = 8 * 63
#: reduced method: peak bytes per triangle of each field in flight in the patch stream (the residual
#: product's rows and columns and the neighbour distances; two fields at a time on two cores), and
#: per triangle of one block of its features' temporaries (:data:`patches.STREAM_BLOCK`). Measured
#: (``bench_core.py --scale``): the Segmenter's rise of the peak RSS 1,104 MB at 1.03M triangles × 20
#: fields, 253 MB at 107k × 4, priced at 0.94 and 0.93 of it
STREAM_BYTES_PER_TRIANGLE_FIELD = 460.0
STREAM_BYTES_PER_BLOCK_TRIANGLE = 1100.0
DEFAULT_BUDGET = 2 * 1024 ** 3


@dataclasses.dataclass
class Estimate:
    triangles: int
    fields: int
    units: int
    memory_bytes: float
    seconds: float
    reduced: bool

    def describe(self, base_bytes: float | None = None, blender_bytes: float = 0.0) -> str:
        """One line: the method, the peak memory and the time. With ``base_bytes`` (what the process
        holds before the fit, :func:`resident_bytes`) the peak is the process's: that, the fit's own
        estimate and ``blender_bytes`` (Blender loaded for the outputs, :data:`BLENDER_OUTPUT_BYTES`),
        each named; without, the fit's own (what it adds to a running Blender: the panel)."""
        how = (f"reduced method on about {self.units} patches" if self.reduced
               else f"full method on {self.triangles} triangles")
        if base_bytes is None:
            mem = f"about {format_bytes(self.memory_bytes)} peak"
        else:
            parts = [f"this process's {format_bytes(base_bytes)}", f"{format_bytes(self.memory_bytes)} for the fit"]
            if blender_bytes:
                parts.append(f"about {format_bytes(blender_bytes)} for Blender's outputs")
            mem = (f"about {format_bytes(base_bytes + self.memory_bytes + blender_bytes)} peak ("
                   + ", ".join(parts[:-1]) + " and " + parts[-1] + ")")
        return f"estimate: {how}, {self.fields} fields: {mem}, {format_seconds(self.seconds)}"


#: what the command line's Blender outputs (--blend/--glb/--fbx/--png) add to its process when it has
#: not loaded Blender to read its input: the bpy module and the scene built (the rise of the peak RSS
#: over the fit's own with --glb: bpy 5.2 254-277 MB on RiggedSimple, CesiumMan, the wolf and the cow;
#: importing bpy alone 245 MB, 4.5's 216 MB)
BLENDER_OUTPUT_BYTES = 260 * 2 ** 20


def resident_bytes() -> float | None:
    """This process's resident memory now, in bytes (Linux: ``/proc/self/status``), else its peak so
    far (``resource``: kB on Linux, bytes on macOS), or None (Windows)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        import resource
        import sys
        peak = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        return peak if sys.platform == "darwin" else peak * 1024
    except (ImportError, OSError, ValueError):
        return None


def format_seconds(seconds: float) -> str:
    """'under 1 s', '45 s', '12 min', '2.5 h': an estimate's time as the command line and the panel show it."""
    if seconds < 1.0:
        return "under 1 s"
    if seconds < 120.0:
        return f"{seconds:.0f} s"
    if seconds < 7200.0:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


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
#: tracked scans: the articulation stage (the relabelling's skin decompositions and link swaps, the
#: refined skin, the split stage; on a vertex sample and at most 64 fields, the skin polished and
#: extended on every vertex and field): seconds per link × vertex ×
#: field, per link, and per link² (the swap and split trials grow with the links, and each round of
#: a trial updates every link's motion in turn). Fitted (minimax of the log ratio) to the fixed fits of
#: the 16 shared sets and pose kinds (2 to 36 links, 96 to 11,666 vertices, 5 to 400 fields; two runs,
#: ``benchmarks/results/estimate.md``): 0.66-1.88 x of the measured time (cheburashka's split trials
#: the high end); without the link² term the Fox's 22 links and RobotExpressive's 36 are underpriced
SKIN_SECONDS_PER_LINK_VERTEX_FIELD = 9.0e-7
SKIN_SECONDS_PER_LINK = 0.018
SKIN_SECONDS_PER_LINK_SQUARED = 0.0013
#: ... where the decompositions run on a vertex sample (``skinning.SAMPLE_VERTICES``, at most half the
#: mesh) the first term stops growing with the mesh: it counts at most this many vertices, and every
#: vertex adds the full-mesh skins' cost (weights extended from the sample, the polish). Fitted to the
#: generated branching scans (``benchmarks/generate.py``, 11 links, 20 fields): 1.26 x of the
#: measured time at 1.03M triangles (0.46 x without this cap), 0.52 x at 107k (0.24 x); their small
#: sizes, whose skins explain the poses at once, stay overpriced (0.27-0.40 x at 4k-17k triangles)
SKIN_SAMPLED_VERTICES = 12000
SKIN_SECONDS_PER_LINK_VERTEX_FIELD_ALL = 1.0e-7
#: ... and where the scan is above the swaps' budget (no swap or split trials: the relabelling's and
#: the refined skin's decompositions only) the first term is this share of its price, on the fields
#: the decompositions use (at most ``skinning.SAMPLE_FIELDS``). Measured (``estimate.md``): the cow at 87
#: fresh poses (11,666 vertices × 64 trial fields) spends 2.6 s in its articulation stages without the
#: trials, 9.7 s with them: 0.27 (without them its estimate was 18.8 s for a 5.4 s fit)
NO_TRIALS_SHARE = 0.25
#: the segmentation's merge to k links (Λ merge, the links' medoids, the seam refinement): seconds
#: per clustered unit × field clustered
MERGE_SECONDS_PER_UNIT_FIELD = 5.5e-6
#: tracked scans with more fields are segmented on this many (``fit.SEGMENT_FIELDS``)
SEGMENT_FIELDS = 64
#: a ``--links auto`` search (:mod:`linkcount`): the tree's error curve segments the scan at e(1) and
#: from ``max_links`` down to where the big drop ends (:func:`linkcount.descending_curve`), about
#: ``CURVE_SHARE`` of the counts (CesiumMan 17-20 of 30, the CraGL sets 15-18, RobotExpressive 30 of
#: 54, the small rigid sets all), each a merge as below plus ``CURVE_SECONDS_PER_COUNT``; then about
#: ``AUTO_WHOLE_FITS`` fits at ``AUTO_LINKS_SHARE`` of Max Links (fits run up to their split stage,
#: the chosen count finished, whole fits where grown links do not settle a decision, the drop of
#: links that are not bones) and ``AUTO_GROWN_LINKS`` grown links. Fitted with the link² term of the
#: fits (``benchmarks/links_auto.py``: the shared sets' searches within 2 x on 8 of 15, 0.30-2.90 x;
#: 3 fits and 8 grown links gave 8 of 15 at 0.33-3.45 x). What the counts cannot tell is how many fits
#: the decisions take: 1 (CesiumMan's fresh poses, the wolf, the rigid sets: 0.30-0.57 x, 1-8 s) to 10
#: (RobotExpressive's fresh poses, its tree pick 8 links short: 2.9 x)
CURVE_SHARE = 0.6
CURVE_SECONDS_PER_COUNT = 0.0
AUTO_WHOLE_FITS = 2.5
AUTO_GROWN_LINKS = 4
#: the fits a search keeps in memory (the chosen count's, those of the counts around it)
AUTO_KEPT_FITS = 3.0
#: the search's peak memory beyond one fit's, per link × vertex × field (fitted to the shared sets'
#: searches, ``benchmarks/links_auto.py``: 0.44-2.26 x of the measured peak RSS rise, the ends
#: RiggedSimple's 5 MB and RobotExpressive's fresh poses, ten whole fits kept)
AUTO_BYTES_PER_LINK_VERTEX_FIELD = 10.0
#: the search's fits are priced at this share of Max Links (the shared sets' searches end at
#: 0.6-0.7 of the ``max(30, 1.5 × true)`` the benchmark gives them; 20 of the default 30)
AUTO_LINKS_SHARE = 2 / 3
#: the same work in fixed-count fits, for the search's progress (:class:`linkcount.SearchProgress`):
#: a count of the curve, a link grown on a decomposition (:func:`linkcount.grow_link`)
CURVE_FITS_PER_COUNT = 0.06
GROW_FITS = 0.15
#: what any fit adds to the process beyond its arrays (the modules it loads, small temporaries):
#: with it the estimate is 0.6-1.2 x the measured rise of the peak RSS on the shared sets
#: (``benchmarks/results/estimate.md``)
FIT_BASE_BYTES = 8 * 2 ** 20
#: the units' features held during the articulation stages, in copies (the Segmenter's and the
#: working copies of the links' medoids and robust motions). Measured (``estimate.md``, the fit's rise
#: of the peak RSS after a warm-up fit): with one copy dembones\_bone (400 fields) 44 MB against 97 MB,
#: CesiumMan at 87 fresh poses 48 against 104, the wolf at 87 75 against 155 (0.45-0.49 x); with three
#: 0.63-0.94 x on the shared sets at their own and at 87 fresh poses, the generated scans 1.1-1.4 x
ARTICULATION_FEATURE_COPIES = 3
#: bytes per vertex × link of the refined skin's per-vertex arrays (errors, their order, the
#: candidate masks, the link statistics), and per vertex of one block of the weight solve
SKIN_BYTES_PER_VERTEX_LINK = 48.0
SOLVE_BYTES_PER_VERTEX = 8.0 * 9 * 9 * 6


#: what a pool worker holds before its first task (Python, numpy, scipy, the core imported)
POOL_PROCESS_BYTES = 90 * 2 ** 20


def stream_bytes(triangles: int, fields: int, jobs: int = 1) -> float:
    """Peak bytes of the reduced method's patch stream (``segmenter.Segmenter``), summed over the
    fit's processes: what every triangle keeps of the field in flight and a block of its
    temporaries (:func:`patches.neighbour_distances`); one field in this process, or with a pool
    (``jobs`` > 1, from :data:`parallel.POOL_TRIANGLES`) one per worker, each worker's own
    :data:`POOL_PROCESS_BYTES` added."""
    from .parallel import POOL_TRIANGLES
    from .patches import STREAM_BLOCK
    one = (STREAM_BYTES_PER_TRIANGLE_FIELD * triangles
           + STREAM_BYTES_PER_BLOCK_TRIANGLE * min(triangles, STREAM_BLOCK))
    if jobs <= 1 or triangles < POOL_TRIANGLES or fields < 2:
        return one
    workers = min(jobs, fields)
    return workers * (one + POOL_PROCESS_BYTES)


def articulation_cost(vertices: int, fields: int, links: int) -> tuple[float, float]:
    """(seconds, bytes) of a tracked scan's articulation stage (skin decompositions). Above the swaps'
    budget (vertices × the fields the trials use) there are no swap or split trials: the sampled
    decompositions' term is then :data:`NO_TRIALS_SHARE` of its price, on those fields."""
    from .skinning import SAMPLE_FIELDS, SOLVE_BLOCK
    from .swaps import within_budget
    trial_fields = min(fields, SAMPLE_FIELDS)
    swaps = within_budget(vertices, trial_fields)
    sampled = SKIN_SECONDS_PER_LINK_VERTEX_FIELD * min(vertices, SKIN_SAMPLED_VERTICES)
    sampled *= fields if swaps else NO_TRIALS_SHARE * trial_fields
    secs = links * (sampled + SKIN_SECONDS_PER_LINK_VERTEX_FIELD_ALL * vertices * fields + SKIN_SECONDS_PER_LINK
                    + SKIN_SECONDS_PER_LINK_SQUARED * links)
    solve_rows = vertices if swaps else min(vertices, SOLVE_BLOCK)   # swaps keep the whole systems
    mem = SKIN_BYTES_PER_VERTEX_LINK * vertices * (links + 1) + SOLVE_BYTES_PER_VERTEX * solve_rows
    return secs, mem


def estimate(triangles: int, fields: int, vertices: int, strategy: str = "summed",
             budget: float = DEFAULT_BUDGET, units: int | None = None, links: int | None = None,
             auto: bool = False, max_links: int | None = None, jobs: int = 1) -> Estimate:
    """Estimate a fit; ``reduced`` says whether the full method would exceed ``budget`` bytes
    (or is chosen for speed, :func:`faster_reduced`). Tracked scans (``strategy`` "summed") add
    the merge to ``links`` links and the articulation stage (default :data:`DEFAULT_LINKS`);
    ``auto`` prices a ``--links auto`` search up to ``max_links`` (default 30) instead: the tree's
    error curve, :data:`AUTO_WHOLE_FITS` fits at :data:`AUTO_LINKS_SHARE` of ``max_links`` links and
    :data:`AUTO_GROWN_LINKS` grown links (the fits it keeps are in the memory). ``jobs``: the fit's
    processes (the memory is summed over them)."""
    full = full_memory(triangles, fields, vertices)
    reduced = full > budget or faster_reduced(triangles, fields, budget)
    u = triangles if not reduced else (units or min(triangles, reduced_units(budget, fields)))
    seg_fields = min(fields, SEGMENT_FIELDS) if strategy == "summed" else fields   # the segmented fields
    pairs = u * (u - 1) / 2
    linkages = 1 if strategy == "summed" else fields
    seconds = 2 * pairs * seg_fields / PAIRS_PER_SECOND + linkages * pairs * LINKAGE_SECONDS_PER_ENTRY
    if reduced:
        seconds += triangles * seg_fields * REDUCED_SECONDS_PER_TRIANGLE_FIELD  # streamed features, neighbour distances
        mem = 2 * 8.0 * pairs + FEATURE_BYTES * u * seg_fields + stream_bytes(triangles, seg_fields, jobs) \
            + 8.0 * 3 * vertices * fields * 2
    else:
        mem = full
    if strategy == "summed":
        m = int(max_links or 30)
        # a search's fits are priced at AUTO_LINKS_SHARE of Max Links (20 of the default 30)
        L = int(links or (max(1, round(AUTO_LINKS_SHARE * m)) if auto else DEFAULT_LINKS))
        merge = MERGE_SECONDS_PER_UNIT_FIELD * u * seg_fields
        secs, skin_mem = articulation_cost(vertices, fields, L)
        mem = max(mem, skin_mem + 8.0 * 3 * vertices * fields * 2
                  + ARTICULATION_FEATURE_COPIES * FEATURE_BYTES * u * seg_fields)
        if auto:
            seconds += CURVE_SHARE * m * (merge + CURVE_SECONDS_PER_COUNT) + AUTO_WHOLE_FITS * (merge + secs) \
                + AUTO_GROWN_LINKS * GROW_FITS * secs
            # the fits the search keeps (their residuals, skins and motions), and what its fits and grown
            # links hold per link, vertex and field (AUTO_BYTES_PER_LINK_VERTEX_FIELD)
            mem += (AUTO_KEPT_FITS + 2) * 8.0 * (2 * 3 * vertices * fields + vertices * L + 12 * fields * L) \
                + AUTO_BYTES_PER_LINK_VERTEX_FIELD * vertices * fields * L
        else:
            seconds += merge + secs
    elif auto:
        seconds *= 2.0          # Green's scans: the tree's curve only, a segmentation a count
    return Estimate(triangles, fields, u, mem + FIT_BASE_BYTES, seconds, reduced)


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
