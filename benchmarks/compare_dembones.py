"""artdef against Dem Bones (``py-dem-bones``, SSDR) on the same tracked scans.

Prints, per scan, side by side: time, articulation-only reconstruction error (Karni–Gotsman
percentage, one formula for both methods), links/bones found, and where the truth is known the
segmentation agreement (adjusted Rand index against the true face labels) and the joint error.
Then the "never collapses" count over 20 random pose sets of the three-link rod.

Scans: every ``*.npz`` under ``--data`` (default ``../shared/data`` beside the repository), plus
fresh random poses (``samples.random_poses``, 20 fields, up to 45° a bone) of the rigged
single-root sets. artdef and Dem Bones get the same number of links/bones: the number of true
links (bones owning a face) where the truth is known, ``--bone-count`` (default 10, the middle
of the 5/10/20 that Dem Bones' own example runs on its sample animation) for ``dembones_bone``.

Error: X (P, N, 3) the deformed positions, X̄ each frame's centroid broadcast over its vertices, X̂ the
articulation only (no residual shapes), error = 100·‖X − X̂‖_F / ‖X − X̄‖_F: the Karni–Gotsman
distortion as the skinning-decomposition papers quote it (``quality.kg_distortion``; docs/metrics.md).
Older tables that used each vertex's mean over the fields for X̄ (larger figures) say so. For artdef
X̂ = Σ_l w_l G_l x0 with G the forward kinematics of the fitted pose parameters; for Dem Bones
X̂ = Σ_b w_b M_b x0 with its per-frame bone matrices.

Joint error (artdef only; Dem Bones gives no joints): for each true joint between two bones that
both own faces, the distance from the true joint (the child bone's rest head) to the fitted joint
between the fitted links matched to those bones (:func:`artdef_addon.quality.true_joint_errors`,
the tests' definition: each true bone → the fitted link holding most of it among the links it is
the majority of), as % of the bounding-box diagonal. When a true bone is the majority of no link,
or both bones end in one link, the joint counts as missed ("merged").

Usage (from the repository root):

    .venv/bin/python benchmarks/compare_dembones.py [--data ../shared/data] [--quick]

``--quick`` skips the scans above 10k triangles. The Markdown tables are written to
``benchmarks/results/compare_dembones.md`` (``--out``).
"""
from __future__ import annotations

import argparse
import glob
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

import artdef_addon  # noqa: E402
from artdef_addon import model, pipeline as PL, procs, quality, samples, segmenter as SG  # noqa: E402
from artdef_addon.scan import Scan, ScanError, validate_scan  # noqa: E402
from artdef_addon.options import FitOptions  # noqa: E402
from peak import reset_peak, status_kb  # noqa: E402

#: the main fit's processes (``--jobs``; 0: one per core, the default of FitOptions.jobs)
JOBS = 0

try:
    from py_dem_bones.portable import _prepare_solver, _read_skinning_result
    import py_dem_bones
    DEMBONES = f"py-dem-bones {py_dem_bones.__version__} (Dem Bones {py_dem_bones.__dem_bones_version__})"
    DEMBONES_ERROR = None
except Exception as exc:  # noqa: BLE001 — report any import failure, still run artdef
    DEMBONES = None
    DEMBONES_ERROR = f"{type(exc).__name__}: {exc}"


# --------------------------------------------------------------------------- measures
def kg_error(X: np.ndarray, Xhat: np.ndarray) -> float:
    """Karni–Gotsman distortion 100·‖X − X̂‖_F / ‖X − X̄‖_F, X̄ each frame's centroid (docs/metrics.md)."""
    return quality.kg_distortion(X, Xhat)


def artdef_articulation(res, x0: np.ndarray) -> np.ndarray:
    """The articulation alone, (P, N, 3): LBS of the FK transforms of the fitted pose parameters."""
    Rf, tf = model.forward_kinematics(res.parents, res.heads, res.frames, res.params)
    return np.stack([model.skin(res.weights, Rf[p], tf[p], x0) for p in range(Rf.shape[0])])


def face_labels_from_weights(faces: np.ndarray, weights_nl: np.ndarray) -> np.ndarray:
    """The link of a face = the bone with the largest summed weight over its vertices (the shared data's rule)."""
    return weights_nl[faces].sum(axis=1).argmax(axis=1)


def joint_errors(truth: dict, res, diag: float):
    """Per true joint between two face-owning bones: error (% diag) of artdef's fitted joint, inf if
    the two bones share a link. The definition the tests use (:func:`quality.true_joint_errors`)."""
    _, err = quality.true_joint_errors(res, truth["joints"], truth["parents"], truth["face_labels"])
    return 100.0 * err / diag


# --------------------------------------------------------------------------- methods
def fit_variants():
    """The artdef fits to run: (label, :class:`FitOptions` fields): the refined weights (the default for
    tracked scans) and the paper's seam weights; the first is the main one."""
    return [("artdef refined", {"skin": "refined"}), ("artdef seam", {"skin": "seam"})]


def run_artdef(scan: Scan, L, kw: dict, segmenter=None):
    """One fit; (result, seconds, articulation error %). With a ready ``segmenter`` (distances and trees
    cached by an earlier fit of the same scan) the seconds still count the whole fit: the segmenter's
    own features + cluster time is added."""
    t0 = time.perf_counter()
    res = PL.fit(scan, L, FitOptions(**kw), segmenter=segmenter)
    secs = time.perf_counter() - t0
    if segmenter is not None:
        secs += segmenter.timings.get("features", 0.0) + segmenter.timings.get("cluster", 0.0)
    x0 = scan.vertices
    X = x0[None] + scan.displacements
    err = kg_error(X, artdef_articulation(res, x0))
    return res, secs, err


def cpu_seconds() -> float:
    """CPU time of this process, every thread (OpenMP's and OpenBLAS's included), and of its ended child
    processes (a fit's pool, closed with the fit), in seconds: beside the wall time it shows how many of
    the machine's cores a program kept busy."""
    import resource
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def peak_start() -> int:
    """Reset this process's peak resident size; returns the resident size (kB) it starts from."""
    reset_peak()
    return status_kb("VmRSS")


def peak_mb(start_kb: int) -> float:
    """The rise of this process's peak resident size since :func:`peak_start`, in MB (a fit's pool
    starts only on scans of 100k triangles or vertices, so on these sets this process is all of it)."""
    return max(0, status_kb("VmHWM") - start_kb) / 1024.0


def run_dembones(x0, faces, X, bones: int, nnz: int, iters: int):
    """Dem Bones' whole decomposition (its own initialisation + iterations): weights (N,B), bones, error, s."""
    t0, c0 = time.perf_counter(), cpu_seconds()
    solver = _prepare_solver(x0, X, bones, faces=faces, max_influences=nnz, iterations=iters)
    solver.compute()
    out = _read_skinning_result(solver)
    secs, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    W, M = out.weights, out.transforms                      # (B, N), (P, B, 4, 4)
    Xhat = np.einsum("bn,pbij,nj->pni", W, M[:, :, :3, :3], x0) + np.einsum("bn,pbi->pni", W, M[:, :, :3, 3])
    return dict(weights=W.T, bones=int(solver.nB), error=kg_error(X, Xhat), seconds=secs, cpu=cpu,
                rmse_check=abs(np.sqrt(np.mean(np.sum((X - Xhat) ** 2, axis=-1))) - solver.rmse()))


# --------------------------------------------------------------------------- data
def load_sets(data_dir: str, fresh_fields: int, bone_count: int, max_tri: int | None, seed: int):
    files = sorted(glob.glob(os.path.join(data_dir, "*.npz")))
    if not files:
        print(f"no .npz under {data_dir}: skipping the shared sets")
    for path in files:
        name = os.path.splitext(os.path.basename(path))[0]
        try:
            with np.load(path, allow_pickle=False) as z:
                d = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001
            print(f"skipping {name}: {exc}")
            continue
        if "displacements" not in d:
            print(f"skipping {name}: no tracked displacements")
            continue
        if max_tri and len(d["faces"]) > max_tri:
            print(f"skipping {name} ({len(d['faces'])} triangles > {max_tri}; --quick)")
            continue
        scan = validate_scan(Scan(d["vertices"], d["faces"], displacements=d["displacements"]))
        truth = None
        if "gt_face_labels" in d:
            truth = dict(face_labels=d["gt_face_labels"], joints=d["gt_joints"], parents=d["gt_parents"],
                         weights=d["gt_weights"])
            L = int(len(np.unique(truth["face_labels"])))
        else:
            L = bone_count
        yield name, scan, truth, L
        if truth is not None and int(np.sum(truth["parents"] < 0)) == 1:
            u = samples.random_poses(d["vertices"], d["gt_weights"], d["gt_joints"], d["gt_parents"],
                                     n_fields=fresh_fields, max_deg=45.0, seed=seed)
            yield name + " (fresh poses)", validate_scan(Scan(d["vertices"], d["faces"], displacements=u)), truth, L


# --------------------------------------------------------------------------- main comparison
def _auto_links_fn():
    """The core's link-count chooser (``--links auto``), or None when this core has none."""
    try:
        from artdef_addon.linkcount import choose_links
    except ImportError:
        return None

    def run(seg, L):
        # the CLI's bound (30), raised where the truth has more links, so the answer can reach it
        m = max(30, int(np.ceil(1.5 * L)))
        t0 = time.perf_counter()
        try:
            choice = choose_links(seg, max_links=m)
        except Exception as exc:  # noqa: BLE001
            return dict(error=f"{type(exc).__name__}: {exc}")
        # a whole --links auto run: the chooser plus the segmenter's features and tree it reuses
        secs = time.perf_counter() - t0 + seg.timings.get("features", 0.0) + seg.timings.get("cluster", 0.0)
        return dict(links=int(choice.links), seconds=secs, max_links=m)
    return run


auto_links = _auto_links_fn()
AUTO_MAX_TRI = 6000  # the link-count curve refits up to max(30, 1.5 L) link counts: minutes on big scans


def compare(sets, variants, nnz, iters, repeats=3, cheap=5000):
    """Both methods on every set; times are medians of ``repeats`` runs for sets of at most ``cheap``
    triangles (one run above), every run a whole fit from scratch."""
    rows = []
    for name, scan, truth, L in sets:
        x0 = scan.vertices
        X = x0[None] + scan.displacements
        diag = float(np.linalg.norm(np.ptp(x0, axis=0)))
        reps = repeats if scan.n_faces <= cheap else 1
        row = dict(name=name, T=scan.n_faces, N=scan.n_vertices, P=scan.n_fields, L=L, truth=truth is not None,
                   runs=reps)
        seg = None
        for i, (label, kw) in enumerate(variants):
            try:
                times, cpus, peaks, serial = [], [], [], []
                for _ in range(reps):
                    if i == 0:  # the main fit, from scratch; later variants reuse its distances
                        for jobs in (1, JOBS):      # --jobs 1 and the default, side by side
                            m0 = peak_start()
                            t0, c0 = time.perf_counter(), cpu_seconds()
                            with procs.pooled(jobs or procs.cores()):
                                seg = SG.Segmenter(scan)
                                res = PL.fit(scan, L, FitOptions(**kw), segmenter=seg)
                            secs, cpus_i = time.perf_counter() - t0, cpu_seconds() - c0
                            if jobs == 1:
                                serial.append((secs, cpus_i, peak_mb(m0), res))
                        err = kg_error(X, artdef_articulation(res, x0))
                        cpus.append(cpus_i)
                        peaks.append(peak_mb(m0))
                    else:
                        res, secs, err = run_artdef(scan, L, kw, segmenter=seg)
                    times.append(secs)
                secs = float(np.median(times))
                cpu = float(np.median(cpus)) if cpus else None
            except (ScanError, ValueError) as exc:
                print(f"  {name}: {label} failed: {exc}")
                row[label] = None
                continue
            check = abs(err - res.articulation_error_percent)
            owning = len(np.unique(res.face_labels))
            reduced = any(str(n).startswith("reduced method") for n in (getattr(res, "notes", None) or []))
            r = dict(seconds=secs, cpu=cpu, error=err, links=res.n_links, owning=owning, check=check,
                     reported=res.articulation_error_percent, reduced=reduced)
            if serial:
                one = serial[-1][3]
                r.update(peak=float(np.median(peaks)), serial_seconds=float(np.median([s[0] for s in serial])),
                         serial_cpu=float(np.median([s[1] for s in serial])),
                         serial_peak=float(np.median([s[2] for s in serial])),
                         same_rig=bool(np.array_equal(one.face_labels, res.face_labels)
                                       and np.allclose(one.weights, res.weights, rtol=0, atol=1e-9)
                                       and np.allclose(one.joints, res.joints, rtol=0, atol=1e-9,
                                                       equal_nan=True)))
            if truth is not None:
                r["ari"] = quality.adjusted_rand_index(res.face_labels, truth["face_labels"])
                je = joint_errors(truth, res, diag)
                r["joints"] = je
            row[label] = r
        if auto_links is not None and seg is not None and AUTO_MAX_TRI and scan.n_faces <= AUTO_MAX_TRI:
            row["auto"] = auto_links(seg, L)
        if DEMBONES:
            try:
                m0 = peak_start()
                runs = [run_dembones(x0, scan.faces, X, L, nnz, iters) for _ in range(reps)]
                db = runs[-1]
                db["peak"] = peak_mb(m0)
                db["seconds"] = float(np.median([d["seconds"] for d in runs]))
                db["cpu"] = float(np.median([d["cpu"] for d in runs]))
                lab = face_labels_from_weights(scan.faces, db["weights"])
                db["owning"] = len(np.unique(lab))
                if truth is not None:
                    db["ari"] = quality.adjusted_rand_index(lab, truth["face_labels"])
                row["dembones"] = db
            except Exception as exc:  # noqa: BLE001
                print(f"  {name}: Dem Bones failed: {type(exc).__name__}: {exc}")
                row["dembones"] = None
        rows.append(row)
        print(line(row, variants), flush=True)
    return rows


def _fmt_joints(je):
    if je is None or len(je) == 0:
        return "—"
    ok = je[np.isfinite(je)]
    miss = int(np.sum(~np.isfinite(je)))
    if ok.size == 0:
        return f"all {len(je)} missed"
    s = f"{np.median(ok):.2f} / {ok.max():.2f} ({int(np.sum(ok <= 2.0))}/{len(je)} ≤ 2%)"
    return s + (f", {miss} merged" if miss else "")


def _fmt_auto(row) -> str:
    au = row.get("auto")
    if not au:
        return "n/a"
    if "links" not in au:
        return "failed"
    off = 100.0 * (au["links"] - row["L"]) / row["L"]
    r0 = next((v for k, v in row.items() if k.startswith("artdef") and isinstance(v, dict)), None)
    ratio = f", {au['seconds'] / r0['seconds']:.1f}× the fixed-count fit" if r0 and r0.get("seconds") else ""
    return f"{au['links']} ({off:+.0f}%), {au['seconds']:.1f} s{ratio}"


def line(row, variants) -> str:
    parts = [f"{row['name']}: T={row['T']} P={row['P']} L={row['L']}"]
    for label, _ in variants:
        r = row.get(label)
        if r:
            cpu = f" (CPU {r['cpu']:.2f}s)" if r.get("cpu") is not None else ""
            s = f"{label}{' (reduced method)' if r.get('reduced') else ''} {r['seconds']:.2f}s{cpu} err {r['error']:.2f}% links {r['owning']}"
            if "ari" in r:
                s += f" ARI {r['ari']:.3f} joints {_fmt_joints(r['joints'])}"
            if r["check"] > 1e-6:
                s += f" (the result reports {r['reported']:.4f}%)"
            parts.append(s)
    au = row.get("auto")
    if au:
        parts.append(f"links auto {au['links']} ({au['seconds']:.1f}s)" if "links" in au else f"links auto failed: {au['error']}")
    db = row.get("dembones")
    if db:
        s = f"Dem Bones {db['seconds']:.2f}s (CPU {db['cpu']:.2f}s) err {db['error']:.2f}% bones {db['bones']} (owning faces {db['owning']})"
        if "ari" in db:
            s += f" ARI {db['ari']:.3f}"
        parts.append(s)
    return "; ".join(parts)


def tables(rows, variants) -> str:
    labels = [v[0] for v in variants]
    head = ["scan", "triangles", "fields", "links/bones"]
    head += [f"{lb} time (s)" for lb in labels] + ["Dem Bones time (s)"]
    head += [f"{lb} error (%)" for lb in labels] + ["Dem Bones error (%)"]
    head += [f"{lb} / Dem Bones error" for lb in labels] + [f"{labels[0]} / Dem Bones time"]
    out = ["### Time and articulation-only reconstruction error", "",
           "| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for row in rows:
        db = row.get("dembones")
        r0 = row.get(labels[0])
        mark = " (reduced method)" if r0 and r0.get("reduced") else ""
        cells = [row["name"].replace("_", "\\_") + mark, f"{row['T']:,}", str(row["P"]), str(row["L"])]
        cells += [f"{row[lb]['seconds']:.2f}" if row.get(lb) else "failed" for lb in labels]
        cells += [f"{db['seconds']:.2f}" if db else "n/a"]
        cells += [f"{row[lb]['error']:.2f}" if row.get(lb) else "failed" for lb in labels]
        cells += [f"{db['error']:.2f}" if db else "n/a"]
        cells += [f"{row[lb]['error'] / db['error']:.2f}" if row.get(lb) and db and db["error"] > 0 else "—"
                  for lb in labels]
        cells += [f"{r0['seconds'] / db['seconds']:.2f}" if r0 and db and db["seconds"] > 0 else "—"]
        out.append("| " + " | ".join(cells) + " |")
    lb0 = labels[0]
    out += ["", "### Cores kept busy: wall time against CPU time", "",
            "CPU time counts every thread of the process (Dem Bones' OpenMP loops, OpenBLAS, artdef's own "
            "threads); cores = CPU / wall. The time bar is on wall time; the CPU ratio is the work each "
            "program does.", "",
            f"| scan | {lb0} wall (s) | {lb0} CPU (s) | {lb0} cores | Dem Bones wall (s) | Dem Bones CPU (s) "
            "| Dem Bones cores | wall ratio | CPU ratio |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        db, r0 = row.get("dembones"), row.get(lb0)
        if not (db and r0 and r0.get("cpu") and db["seconds"] > 0 and db["cpu"] > 0):
            continue
        out.append("| " + " | ".join([
            row["name"].replace("_", "\\_"), f"{r0['seconds']:.2f}", f"{r0['cpu']:.2f}",
            f"{r0['cpu'] / r0['seconds']:.2f}", f"{db['seconds']:.2f}", f"{db['cpu']:.2f}",
            f"{db['cpu'] / db['seconds']:.2f}", f"{r0['seconds'] / db['seconds']:.2f}",
            f"{r0['cpu'] / db['cpu']:.2f}"]) + " |")
    out += ["", "### Processes: `--jobs 1` against the default, beside Dem Bones", "",
            f"The main fit ({lb0}) run with one process and with the default (one per core), side by side; "
            "peak: the rise of the resident peak over the fit (MB, every process of it).", "",
            "| scan | jobs 1 wall (s) | jobs 1 CPU (s) | jobs 1 peak (MB) | default wall (s) | default CPU (s) "
            "| default peak (MB) | same rig | Dem Bones wall (s) | Dem Bones CPU (s) | Dem Bones peak (MB) "
            "| default / Dem Bones wall |",
            "|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|"]
    for row in rows:
        db, r0 = row.get("dembones"), row.get(lb0)
        if not (r0 and "serial_seconds" in r0):
            continue
        dbc = [f"{db['seconds']:.2f}", f"{db['cpu']:.2f}", f"{db.get('peak', 0):.0f}",
               f"{r0['seconds'] / db['seconds']:.2f}"] if db else ["n/a"] * 4
        out.append("| " + " | ".join([
            row["name"].replace("_", "\\_"), f"{r0['serial_seconds']:.2f}", f"{r0['serial_cpu']:.2f}",
            f"{r0['serial_peak']:.0f}", f"{r0['seconds']:.2f}", f"{r0['cpu']:.2f}", f"{r0['peak']:.0f}",
            "yes" if r0["same_rig"] else "no", *dbc]) + " |")
    out += ["", "### Structure (scans with a true skeleton)", "",
            "| scan | true links | artdef links | links auto | Dem Bones bones (owning faces) | ARI artdef | ARI Dem Bones "
            "| artdef joint error, median / max % of diagonal (≤ 2%) |",
            "|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in rows:
        if not row["truth"]:
            continue
        r = row.get(lb0)
        db = row.get("dembones")
        out.append("| " + " | ".join([
            row["name"].replace("_", "\\_"), str(row["L"]),
            str(r["owning"]) if r else "failed",
            _fmt_auto(row),
            f"{db['bones']} ({db['owning']})" if db else "n/a",
            f"{r['ari']:.3f}" if r else "—",
            f"{db['ari']:.3f}" if db else "n/a",
            _fmt_joints(r["joints"]) if r else "—"]) + " |")
    return "\n".join(out)


# --------------------------------------------------------------------------- never collapses
def collapse_test(n_sets, nnz, iters, ari_ok=0.95):
    rows = []
    for s in range(n_sets):
        p = 3 + s % 8
        scan, truth = samples.rod(n_fields=p, seed=s)
        res = artdef_addon.fit(scan, 3)
        a_links = len(np.unique(res.face_labels))
        a_ari = quality.adjusted_rand_index(res.face_labels, truth["face_labels"])
        row = dict(seed=s, P=p, artdef_links=a_links, artdef_ari=a_ari)
        if DEMBONES:
            x0 = scan.vertices
            X = x0[None] + scan.displacements
            db = run_dembones(x0, scan.faces, X, 3, nnz, iters)
            lab = face_labels_from_weights(scan.faces, db["weights"])
            row.update(db_bones=db["bones"], db_owning=len(np.unique(lab)),
                       db_ari=quality.adjusted_rand_index(lab, truth["face_labels"]))
        rows.append(row)
        print(f"  rod seed {s:2d}, {p:2d} fields: artdef {a_links} links ARI {a_ari:.3f}"
              + (f"; Dem Bones {row['db_bones']} bones, {row['db_owning']} owning faces, ARI {row['db_ari']:.3f}"
                 if DEMBONES else ""), flush=True)
    ok = sum(r["artdef_links"] == 3 and r["artdef_ari"] >= ari_ok for r in rows)
    md = ["### Never collapses: three-link rod, 20 random pose sets (3–10 fields)", "",
          f"artdef finds 3 distinct links with ARI ≥ {ari_ok} on **{ok}/{len(rows)}** sets "
          f"(median ARI {np.median([r['artdef_ari'] for r in rows]):.3f}, min {min(r['artdef_ari'] for r in rows):.3f})."]
    if DEMBONES:
        fewer = sum(r["db_bones"] < 3 for r in rows)
        fewer_own = sum(r["db_owning"] < 3 for r in rows)
        db_ok = sum(r["db_owning"] == 3 and r["db_ari"] >= ari_ok for r in rows)
        md.append(f"Dem Bones (its own initialisation, 3 bones requested) ends with fewer than 3 bones on "
                  f"**{fewer}/{len(rows)}** sets, with fewer than 3 bones owning a face on **{fewer_own}/{len(rows)}**, "
                  f"and matches the 3 true links (ARI ≥ {ari_ok}) on {db_ok}/{len(rows)} "
                  f"(median ARI {np.median([r['db_ari'] for r in rows]):.3f}).")
    md += ["", "| seed | fields | artdef links | artdef ARI | Dem Bones bones | Dem Bones bones owning faces | Dem Bones ARI |",
           "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        md.append(f"| {r['seed']} | {r['P']} | {r['artdef_links']} | {r['artdef_ari']:.3f} | "
                  + (f"{r['db_bones']} | {r['db_owning']} | {r['db_ari']:.3f} |" if DEMBONES else "n/a | n/a | n/a |"))
    return "\n".join(md)


def auto_samples():
    """``--links auto`` on the generated samples, where it must land exactly on the true count."""
    sys.path.insert(0, HERE)
    from generate import branching_scan
    cases = [("rod, 3 fields", lambda: samples.rod(n_fields=3)),
             ("rod, 8 fields", lambda: samples.rod(n_fields=8, seed=5)),
             ("branching, 12 fields", lambda: samples.branching()),
             ("branching, 2% noise + bulges", lambda: samples.branching(noise=0.02, bulges=True)),
             ("branching, disconnected", lambda: samples.branching(disconnected=True)),
             ("generated branching (1.1k triangles, 10 random LBS poses)", lambda: branching_scan(1000, 10, seed=3))]
    md = ["### Link count chosen automatically on the generated samples", "",
          "| sample | true links | links auto | seconds |", "|---|---:|---:|---:|"]
    for name, make in cases:
        scan, truth = make()
        L = int(len(np.unique(truth["face_labels"])))
        seg = SG.Segmenter(scan)
        au = auto_links(seg, L)
        cell = str(au["links"]) if "links" in au else "failed: " + au["error"]
        md.append(f"| {name} | {L} | {cell} | {au.get('seconds', float('nan')):.1f} |")
        print(f"  {name}: true {L}, auto {cell}", flush=True)
    return "\n".join(md)


def main(argv=None):
    ap = argparse.ArgumentParser(description="artdef vs py-dem-bones on the shared tracked scans.")
    ap.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data"))
    ap.add_argument("--quick", action="store_true", help="skip scans above 10k triangles")
    ap.add_argument("--bone-count", type=int, default=10, help="links/bones for scans without truth (dembones_bone)")
    ap.add_argument("--fresh-fields", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1, help="seed of the fresh random poses")
    ap.add_argument("--nnz", type=int, default=4, help="Dem Bones influences per vertex (artdef's refined uses 4)")
    ap.add_argument("--iters", type=int, default=30, help="Dem Bones global iterations (its default 30)")
    ap.add_argument("--rod-sets", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats (median) for scans of ≤ 5k triangles")
    ap.add_argument("--only", help="comma-separated substrings: run only the scans whose name contains one")
    ap.add_argument("--skip-rod", action="store_true")
    ap.add_argument("--skip-auto-samples", action="store_true")
    ap.add_argument("--auto-max-triangles", type=int, default=6000,
                    help="run --links auto only on scans up to this size (0: never)")
    ap.add_argument("--jobs", type=int, default=0,
                    help="processes of the main fit beside its --jobs 1 run (0: one per core, the default)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "compare_dembones.md"))
    a = ap.parse_args(argv)
    global JOBS
    JOBS = a.jobs
    t_all = time.perf_counter()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    env = (f"{platform.machine()}, {cores} cores, Python {platform.python_version()}, numpy {np.__version__}; "
           f"{DEMBONES or 'py-dem-bones NOT available: ' + DEMBONES_ERROR}. Shared machine: timings are noisy.")
    print(env)
    global AUTO_MAX_TRI
    AUTO_MAX_TRI = a.auto_max_triangles
    variants = fit_variants()
    print("artdef fits:", ", ".join(f"{lb} {kw or ''}" for lb, kw in variants))
    sets = load_sets(a.data, a.fresh_fields, a.bone_count, 10000 if a.quick else None, a.seed)
    if a.only:
        keys = a.only.split(",")
        sets = (s for s in sets if any(k in s[0] for k in keys))
    rows = compare(sets, variants, a.nnz, a.iters, a.repeats)
    md = ["# artdef vs Dem Bones", "", env, "",
          f"Same link/bone count for both (true links; {a.bone_count} for dembones\\_bone, as in Dem Bones' example). "
          f"Dem Bones: `solve_skinning`, {a.nnz} influences per vertex, {a.iters} iterations. Error: articulation only, "
          "100·‖X−X̂‖/‖X−X̄‖, X̄ each frame's centroid (Karni–Gotsman distortion). Fresh poses: 20 random LBS poses of the true rig (≤ 45° a bone). "
          f"Times: median of {a.repeats} whole runs for scans of ≤ 5k triangles, one run above. "
          f"Links auto: the core's chooser (`linkcount.choose_links`, up to max(30, 1.5·true) links) on scans of "
          f"≤ {a.auto_max_triangles} triangles; the % is its distance from the true count.", "",
          tables(rows, variants), ""]
    print("\n".join(md[6:]))
    if auto_links is not None and not a.skip_auto_samples:
        print("links auto on the generated samples:", flush=True)
        au_md = auto_samples()
        md += [au_md, ""]
        print(au_md)
    if not a.skip_rod:
        print("never collapses (three-link rod):", flush=True)
        rod_md = collapse_test(a.rod_sets, a.nnz, a.iters)
        md += [rod_md, ""]
        print(rod_md)
    md.append(f"Script wall time: {time.perf_counter() - t_all:.0f} s.")
    print(md[-1])
    if a.out:
        os.makedirs(os.path.dirname(a.out), exist_ok=True)
        with open(a.out, "w") as fh:
            fh.write("\n".join(md) + "\n")
        print("wrote", a.out)


if __name__ == "__main__":
    main()
