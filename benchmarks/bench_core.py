"""Core benchmark: prints figures, asserts nothing.

(a) ε throughput: ``metric.condensed_distance`` for one field of T triangles (every pair,
    both residual directions, the |·| distance, packed into the condensed vector) against a plain
    dense product ``A @ B.T`` of two (T, 17) float64 arrays into a T×T result — the same inner
    dimension and output shape as the residual GEMM. Median seconds of ``--repeats`` runs.
(b) End to end: ``pipeline.fit`` on generated articulated scans (``generate.branching_scan``, 11 links)
    of about 1k, 5k, 20k triangles × 10 and 50 fields; seconds per stage, peak resident memory of
    a fresh subprocess per case (``VmHWM``, and the part above the resident size just before the
    fit), the adjusted Rand index against the true face labels and the articulation-only error.

Usage (from the repository root):

    .venv/bin/python benchmarks/bench_core.py            # full: 1k/5k/20k × 10/50 (minutes)
    .venv/bin/python benchmarks/bench_core.py --quick    # 1k/5k × 10/50, T up to 5k for (a)
    .venv/bin/python benchmarks/bench_core.py --sizes 20000 --fields 20 --skip-eps
    .venv/bin/python benchmarks/bench_core.py --scale    # 20k/100k/1M × 20/200, full vs reduced
    .venv/bin/python benchmarks/bench_core.py --sizes 20000 --fields 50 --skip-eps --dembones

``--method full|reduced|both`` forces the core's full or reduced (patch) method (``auto`` lets the
core choose from its memory budget); ``both`` runs the full method where it fits in 70% of RAM and
the reduced one, and prints the ARI between their labels. ``--dembones`` also times py-dem-bones on
the same scan (11 bones) and prints artdef's time / Dem Bones' time. ``--skin`` passes the fit's
skin option (seam/refined).

Results are also written as Markdown to ``benchmarks/results/bench_core.md``, with ``--scale`` to
``benchmarks/results/bench_scale.md`` (``--out`` writes elsewhere).
"""
from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from artdef_addon import metric, quality  # noqa: E402
from artdef_addon import pipeline as PL, segmenter as SG, stages as ST  # noqa: E402
from artdef_addon.options import FitOptions  # noqa: E402
from generate import branching_scan  # noqa: E402
from peak import status_kb as _status_kb  # noqa: E402


def _median_time(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


# ----------------------------------------------------------------------------- (a)
def bench_eps(sizes, repeats: int):
    rows = []
    rng = np.random.default_rng(0)
    for target in sizes:
        scan, _ = branching_scan(target, n_fields=1, seed=1)
        T = scan.n_faces
        f = metric.field_features(scan.vertices, scan.displacements[0], scan.faces)
        t_eps = _median_time(lambda: metric.condensed_distance(f), repeats)
        A = rng.standard_normal((T, 17))
        B = rng.standard_normal((T, 17))
        t_gemm = _median_time(lambda: A @ B.T, repeats)
        pairs = T * (T - 1) // 2
        rows.append(dict(T=T, eps_s=t_eps, eps_pairs_s=pairs / t_eps, gemm_s=t_gemm, gemm_entries_s=T * T / t_gemm,
                         ratio=t_eps / t_gemm))
        r = rows[-1]
        print(f"  T={T:6d}: condensed ε {r['eps_s']:.3f} s ({r['eps_pairs_s']:.3g} pairs/s), "
              f"A@B.T {r['gemm_s']:.3f} s ({r['gemm_entries_s']:.3g} entries/s), ratio {r['ratio']:.2f}", flush=True)
    return rows


def eps_table(rows) -> str:
    out = ["| triangles | pairs T(T−1)/2 | condensed ε (s) | ε pairs/s | A@Bᵀ T×T (s) | GEMM entries/s | ratio ε / GEMM |",
           "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        out.append(f"| {r['T']:,} | {r['T'] * (r['T'] - 1) // 2:,} | {r['eps_s']:.3f} | {r['eps_pairs_s']:.3g} | "
                   f"{r['gemm_s']:.3f} | {r['gemm_entries_s']:.3g} | {r['ratio']:.2f} |")
    return "\n".join(out)


# ----------------------------------------------------------------------------- (b)
def dembones_case(scan, bones: int) -> dict:
    """py-dem-bones' whole decomposition of the same scan (for the time ratio)."""
    from py_dem_bones.portable import solve_skinning
    x0 = scan.vertices
    X = x0[None] + scan.displacements
    t0 = time.perf_counter()
    out = solve_skinning(x0, X, bones, faces=scan.faces, max_influences=4, iterations=30)
    secs = time.perf_counter() - t0
    W, M = out.weights, out.transforms
    Xhat = np.einsum("bn,pbij,nj->pni", W, M[:, :, :3, :3], x0) + np.einsum("bn,pbi->pni", W, M[:, :, :3, 3])
    err = 100 * np.linalg.norm(X - Xhat) / np.linalg.norm(X - X.mean(axis=0))
    return dict(db_s=secs, db_kg=float(err), db_bones=int(W.shape[0]))


def _fit_option(name: str, value):
    """``{name: value}`` for the fit's :class:`FitOptions` (nothing when ``value`` is None)."""
    return {} if value is None else {name: value}


def _segmenter_kw(method: str) -> dict:
    """Force the full or the reduced method when the core's Segmenter has ``reduce=``."""
    if method == "auto":
        return {}
    if "reduce" not in inspect.signature(SG.Segmenter.__init__).parameters:
        raise SystemExit(f"this core has no reduced method: --method {method} is not available")
    return {"reduce": method == "reduced"}


def run_case(target: int, n_fields: int, strategy: str, skin: str | None, dembones: bool = False,
             method: str = "auto", labels_out: str | None = None) -> dict:
    """One end-to-end fit in this process (called in a fresh subprocess by the driver)."""
    t0 = time.perf_counter()
    scan, truth = branching_scan(target, n_fields=n_fields, seed=7)
    t_gen = time.perf_counter() - t0
    rss0 = _status_kb("VmRSS")
    t0 = time.perf_counter()
    seg = SG.Segmenter(scan, strategy=strategy, **_segmenter_kw(method))
    res = PL.fit(scan, truth["n_links"], FitOptions(**_fit_option("skin", skin)), segmenter=seg)
    wall = time.perf_counter() - t0
    peak = _status_kb("VmHWM")
    timings = dict(res.timings)
    timings["total"] = wall  # the Segmenter was built outside fit(): count it
    ari = quality.adjusted_rand_index(res.face_labels, truth["face_labels"])
    out = dict(T=scan.n_faces, N=scan.n_vertices, P=n_fields, generate_s=t_gen, timings=timings,
               peak_mb=peak / 1024, rss_before_mb=rss0 / 1024, ari=ari, links=res.n_links,
               kg=res.articulation_error_percent, skin=getattr(res, "skin", "seam"),
               method="reduced" if getattr(seg, "reduced", False) else "full",
               notes=list(getattr(res, "notes", []) or []))
    if labels_out:
        np.save(labels_out, res.face_labels)
    if dembones:  # after the fit's peak memory was read
        out.update(dembones_case(scan, truth["n_links"]))
    return out


def _child(target, P, a, method, labels_out=None):
    cmd = [sys.executable, os.path.abspath(__file__), "--case", str(target), str(P), "--strategy", a.strategy,
           "--method", method]
    if a.skin:
        cmd += ["--skin", a.skin]
    if a.dembones:
        cmd += ["--dembones"]
    if labels_out:
        cmd += ["--labels-out", labels_out]
    cp = subprocess.run(cmd, capture_output=True, text=True)
    if cp.returncode != 0:
        print(f"  {target}×{P} ({method}): FAILED\n{cp.stderr[-2000:]}", flush=True)
        return None
    return json.loads(cp.stdout.strip().splitlines()[-1])


def full_fits(target: int, P: int, avail: float) -> bool:
    """Whether the full method's condensed matrices (linkage copies the sum) fit in ``avail`` bytes."""
    T = 1072 * max(1, int(round(np.sqrt(target / 1072)))) ** 2
    return 2 * 8.0 * T * (T - 1) / 2 + 8.0 * 63 * T * P < avail


def bench_fit(sizes, fields, a):
    """Every size × field count; ``a.method`` auto/full/reduced, or ``both`` (full where it fits in
    memory, and the reduced method, with the ARI between their labels)."""
    import tempfile
    rows = []
    avail = 0.7 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    for target in sizes:
        for P in fields:
            methods = [a.method] if a.method != "both" else (
                ["full", "reduced"] if full_fits(target, P, avail) else ["reduced"])
            labels = {}
            for method in methods:
                n = a.repeats if target < a.big else 1
                runs = []
                tmp = tempfile.NamedTemporaryFile(suffix=".npy", delete=False).name if a.method == "both" else None
                for _ in range(n):
                    r = _child(target, P, a, method, tmp)
                    if r is None:
                        break
                    runs.append(r)
                if not runs:
                    continue
                if tmp:
                    labels[method] = np.load(tmp)
                    os.unlink(tmp)
                stages = {k: statistics.median(r["timings"][k] for r in runs) for k in runs[0]["timings"]}
                row = dict(runs[0], timings=stages, peak_mb=max(r["peak_mb"] for r in runs), repeats=len(runs))
                if "db_s" in runs[0]:
                    row["db_s"] = statistics.median(r["db_s"] for r in runs)
                if method == "reduced" and "full" in labels and "reduced" in labels:
                    row["ari_full"] = quality.adjusted_rand_index(labels["full"], labels["reduced"])
                rows.append(row)
                st = ", ".join(f"{k} {v:.2f}" for k, v in stages.items())
                print(f"  T={row['T']:7d} P={P:3d} {row['method']:7s} (median of {len(runs)}): {st} s; "
                      f"peak RSS {row['peak_mb']:.0f} MB (+{row['peak_mb'] - row['rss_before_mb']:.0f} over the "
                      f"loaded scan); ARI {row['ari']:.4f}; articulation error {row['kg']:.2f}% ({row['skin']} skin)"
                      + (f"; ARI reduced vs full {row['ari_full']:.4f}" if "ari_full" in row else "")
                      + (f"; Dem Bones {row['db_s']:.2f} s ({row['db_kg']:.2f}%), artdef/Dem Bones time "
                         f"{stages['total'] / row['db_s']:.2f}" if "db_s" in row else ""), flush=True)
                for note in row.get("notes", []):
                    print("    note:", note)
    return rows


def fit_table(rows) -> str:
    names = ["features", "cluster", "merge"] + [n for n, _ in ST.STAGES if n != "segment"]
    extra = sorted({k for r in rows for k in r["timings"]} - set(names) - {"total"})
    cols = names + extra
    db = any("db_s" in r for r in rows)
    agree = any("ari_full" in r for r in rows)
    head = (["triangles", "fields", "method"] + [f"{c} (s)" for c in cols] +
            ["total (s)", "peak RSS (MB)", "Δ RSS in fit (MB)", "ARI vs truth", "articulation error (%)", "runs"]
            + (["ARI reduced vs full"] if agree else [])
            + (["Dem Bones (s)", "Dem Bones error (%)", "artdef / Dem Bones time"] if db else []))
    out = ["| " + " | ".join(head) + " |", "|---:|---:|---|" + "---:|" * (len(head) - 3)]
    for r in rows:
        t = r["timings"]
        cells = [f"{r['T']:,}", str(r["P"]), r.get("method", "full")] + [f"{t.get(c, 0.0):.2f}" for c in cols]
        cells += [f"{t['total']:.2f}", f"{r['peak_mb']:.0f}", f"{r['peak_mb'] - r['rss_before_mb']:.0f}",
                  f"{r['ari']:.4f}", f"{r['kg']:.2f}", str(r["repeats"])]
        if agree:
            cells.append(f"{r['ari_full']:.4f}" if "ari_full" in r else "—")
        if db:
            cells += ([f"{r['db_s']:.2f}", f"{r['db_kg']:.2f}", f"{t['total'] / r['db_s']:.2f}"] if "db_s" in r
                      else ["—", "—", "—"])
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def machine() -> str:
    try:
        import threadpoolctl  # noqa: F401
        blas = "; ".join(f"{d['internal_api']} {d['num_threads']} threads"
                         for d in threadpoolctl.threadpool_info())
    except Exception:
        blas = "BLAS threads: default"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (f"{platform.machine()}, {cores} cores, Python {platform.python_version()}, numpy {np.__version__}, "
            f"{blas}. The machine was shared with other jobs, so timings are noisy.")


def main(argv=None):
    ap = argparse.ArgumentParser(description="artdef core benchmark: ε throughput and end-to-end fits.")
    ap.add_argument("--quick", action="store_true", help="1k and 5k triangles only")
    ap.add_argument("--sizes", help="comma-separated target triangle counts (default 1000,5000,20000)")
    ap.add_argument("--fields", default="10,50", help="comma-separated field counts for (b)")
    ap.add_argument("--repeats", type=int, default=3, help="repeats per timing (median); fits above --big run once")
    ap.add_argument("--big", type=int, default=10000, help="fits of at least this many triangles run once")
    ap.add_argument("--strategy", default="auto", help="fit strategy (auto|summed|paper)")
    ap.add_argument("--skin", default=None, help="fit skin option when the core has it (seam|refined|auto)")
    ap.add_argument("--method", default="auto", choices=("auto", "full", "reduced", "both"),
                    help="full or reduced (patch) method, when the core has it; both = each, with their ARI")
    ap.add_argument("--scale", action="store_true",
                    help="large sizes: 20k/100k/1M triangles × 20/200 fields, --method both, no (a)")
    ap.add_argument("--labels-out", help=argparse.SUPPRESS)
    ap.add_argument("--dembones", action="store_true",
                    help="also time py-dem-bones (11 bones, 4 influences, 30 iterations) on each scan and print the ratio")
    ap.add_argument("--skip-eps", action="store_true")
    ap.add_argument("--skip-fit", action="store_true")
    ap.add_argument("--out", default=None,
                    help="Markdown file (default results/bench_core.md, with --scale results/bench_scale.md)")
    ap.add_argument("--case", nargs=2, type=int, metavar=("TRIANGLES", "FIELDS"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.case:
        print(json.dumps(run_case(a.case[0], a.case[1], a.strategy, a.skin, a.dembones, a.method, a.labels_out)))
        return
    if a.skin and not _fit_option("skin", a.skin):
        print(f"note: this core's fit() has no skin option; ignoring --skin {a.skin}")
        a.skin = None
    if a.out is None:
        a.out = os.path.join(HERE, "results", "bench_scale.md" if a.scale else "bench_core.md")
    if a.scale:
        a.sizes = a.sizes or "20000,100000,1000000"
        a.fields = "20,200" if a.fields == "10,50" else a.fields
        a.method = "both" if a.method == "auto" else a.method
        a.skip_eps = True
    sizes = [int(s) for s in a.sizes.split(",")] if a.sizes else ([1000, 5000] if a.quick else [1000, 5000, 20000])
    fields = [int(s) for s in a.fields.split(",")]
    print("machine:", machine())
    md = ["# bench_core results", "", machine(), ""]
    t_all = time.perf_counter()
    if not a.skip_eps:
        print("(a) ε throughput, one field:", flush=True)
        rows = bench_eps(sizes, a.repeats)
        md += ["## ε throughput (one field)", "", eps_table(rows), ""]
        print(eps_table(rows))
    if not a.skip_fit:
        print(f"(b) end-to-end fit, 11 links, strategy {a.strategy}, a fresh process per case:", flush=True)
        if a.dembones:
            try:
                import py_dem_bones  # noqa: F401
            except Exception as exc:  # noqa: BLE001
                print(f"note: py-dem-bones does not import ({type(exc).__name__}: {exc}); no Dem Bones times")
                a.dembones = False
        rows = bench_fit(sizes, fields, a)
        md += [f"## End-to-end fit (generated branching object, 11 links, strategy {a.strategy}, method {a.method}"
               + (f", skin {a.skin}" if a.skin else "") + ")", "", fit_table(rows), ""]
        notes = sorted({n for r in rows for n in r.get("notes", [])})
        md += [f"- note from the fit: {n}" for n in notes] + ([""] if notes else [])
        print(fit_table(rows))
    md.append(f"Benchmark wall time: {time.perf_counter() - t_all:.0f} s.")
    print(md[-1])
    if a.out:
        os.makedirs(os.path.dirname(a.out), exist_ok=True)
        with open(a.out, "w") as fh:
            fh.write("\n".join(md) + "\n")
        print("wrote", a.out)


if __name__ == "__main__":
    main()
