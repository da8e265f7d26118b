"""Benchmark report: per-dataset tables, GenReg confidence analysis, JSON with every pair, PNG plots.

Inputs are the JSON-ready records of `runner.run_benchmark` (one per pair and method, RE in degrees, TE
and CD in the dataset's units, seconds of wall time, the pair's overlap share, ModelNet40's category) and
the sections of `ablation.run_ablations` (same record fields, one table per dataset). Statistics skip NaN
(a method that raised); such pairs count as failures in the success rate and are listed in the `errors`
column. ModelNet40 tables add RE / TE means and success without the symmetric categories
(`datasets.SYMMETRIC_CATEGORIES`); datasets whose overlap share varies get a success-by-overlap table
(`OVERLAP_BINS`) and a panel of `success_vs_overlap.png`.

`RegistrationResult.confidence` is a calibrated probability that the pose is right, so every table row with
confidences (the GenReg methods) also gives its ROC AUC for the dataset's success rule, its expected
calibration error (`expected_calibration_error`: 10 equal-width bins, as scripts/calibrate_confidence.py)
and the confident-wrong count (confidence >= `CONFIDENT`, failed); `reliability.png` plots the observed
success rate against the confidence per dataset kind.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import mannwhitneyu

from genreg_bench.datasets import SYMMETRIC_CATEGORIES
from genreg_bench.methods import ALL_METHODS, GENREG_METHODS, REFERENCE_METHODS
from genreg_bench.runner import BenchRun

DEFAULT_CONFIDENCE_THRESHOLDS = (0.5, 0.9)
CONFIDENT = 0.5  # a result at or above this confidence claims to be right: confident-wrong if it failed
CALIBRATION_BINS = 10  # equal-width confidence bins of the ECE and the reliability diagram
OVERLAP_BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)  # success-by-overlap bins (the last one closed)
MIN_OVERLAP_SPREAD = 0.1  # a dataset gets the success-by-overlap table and plot when its shares span this
# Figures the GenReg paper (CVPR 2022) reports for a table of ours, shown under that table.
# The paper samples every shape twice from its mesh; here the two clouds are subsets of 1024 given points.
PAPER_REPORTED = {"modelnet-unseen-clean": {"cd": 0.033, "re_deg": 2.093, "te": 0.008}}


def _nanstat(values: Sequence[float], fn: Any) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(fn(v)) if len(v) else float("nan")


def method_order(methods: Iterable[str]) -> list[str]:
    present = set(methods)
    return [m for m in ALL_METHODS if m in present] + sorted(present - set(ALL_METHODS))


def summarize(records: Sequence[dict[str, Any]], cd_floor: Sequence[float] = ()) -> list[dict[str, Any]]:
    """One row per method of one dataset's records (plus a 'ground truth' row with the CD floor).

    Row: method, pairs, errors, cd, re_mean, re_median, te_mean, te_median, success (fraction), ms_median;
    with categories in the records also `asymmetric`: pairs, re_mean, te_mean, success of the pairs outside
    the symmetric categories; with confidences in the records (GenReg) also `calibration` (`calibration_stats`).
    """
    rows = []
    if len(cd_floor):
        rows.append({"method": "ground truth", "pairs": len(cd_floor), "errors": 0,
                     "cd": _nanstat(cd_floor, np.mean), "re_mean": 0.0, "re_median": 0.0, "te_mean": 0.0,
                     "te_median": 0.0, "success": 1.0, "ms_median": float("nan")})
    for m in method_order(r["method"] for r in records):
        rs = [r for r in records if r["method"] == m]
        col = {k: [r[k] for r in rs] for k in ("cd", "re_deg", "te", "seconds")}
        rows.append({
            "method": m, "pairs": len(rs), "errors": sum("error" in r for r in rs),
            "cd": _nanstat(col["cd"], np.mean),
            "re_mean": _nanstat(col["re_deg"], np.mean), "re_median": _nanstat(col["re_deg"], np.median),
            "te_mean": _nanstat(col["te"], np.mean), "te_median": _nanstat(col["te"], np.median),
            "success": float(np.mean([bool(r["success"]) for r in rs])),
            "ms_median": 1e3 * _nanstat(col["seconds"], np.median),
        })
        scored = _with_confidence(rs)
        if scored:
            rows[-1]["calibration"] = calibration_stats([r["confidence"] for r in scored],
                                                        [bool(r["success"]) for r in scored])
        if any("category" in r for r in rs):
            rows[-1]["asymmetric"] = _means([r for r in rs if r.get("category") not in SYMMETRIC_CATEGORIES])
    return rows


def _means(rs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """pairs, re_mean, te_mean and success of some records."""
    return {"pairs": len(rs), "re_mean": _nanstat([r["re_deg"] for r in rs], np.mean),
            "te_mean": _nanstat([r["te"] for r in rs], np.mean),
            "success": float(np.mean([bool(r["success"]) for r in rs])) if rs else float("nan")}


def overlap_bin(share: float) -> int:
    """The index of `share`'s bin in OVERLAP_BINS (the last bin holds 1.0)."""
    return min(int(np.searchsorted(OVERLAP_BINS, share, side="right")) - 1, len(OVERLAP_BINS) - 2)


def varies_in_overlap(info: dict[str, Any]) -> bool:
    shares = [v for v in info.get("overlap") or [] if v is not None]
    return len(shares) > 1 and max(shares) - min(shares) >= MIN_OVERLAP_SPREAD


def success_by_overlap(records: Sequence[dict[str, Any]]) -> dict[str, list[tuple[int, float]]]:
    """{method: [(pairs, success rate) per OVERLAP_BINS bin]} of one dataset's records (NaN: empty bin)."""
    table: dict[str, list[tuple[int, float]]] = {}
    for m in method_order(r["method"] for r in records):
        bins: list[list[bool]] = [[] for _ in OVERLAP_BINS[1:]]
        for r in records:
            if r["method"] == m and r.get("overlap") is not None:
                bins[overlap_bin(r["overlap"])].append(bool(r["success"]))
        table[m] = [(len(b), float(np.mean(b)) if b else float("nan")) for b in bins]
    return table


def overlap_table(records: Sequence[dict[str, Any]]) -> str:
    """Markdown: success rate per overlap bin (columns, with their pair counts), one row per method."""
    table = success_by_overlap(records)
    counts = next(iter(table.values()), [])
    edges = list(itertools.pairwise(OVERLAP_BINS))
    head = "| method | " + " | ".join(f"overlap {lo:.1f}-{hi:.1f} ({n[0]})" for (lo, hi), n in zip(edges, counts)) + " |"
    lines = [head, "|" + "---|" * (1 + len(edges))]
    lines += [f"| {m} | " + " | ".join(_pct(rate) for _, rate in cells) + " |" for m, cells in table.items()]
    return "\n".join(lines)


def roc_auc(scores: Sequence[float], labels: Sequence[bool]) -> float | None:
    """Area under the ROC curve of `scores` for positive `labels` (ties count 1/2); None if one class is empty.

    AUC = P(score of a random positive > score of a random negative) = U / (n_pos n_neg), with U the
    Mann-Whitney statistic of the positives.
    """
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    pos, neg = s[y], s[~y]
    if len(pos) == 0 or len(neg) == 0:
        return None
    return float(mannwhitneyu(pos, neg, alternative="two-sided").statistic / (len(pos) * len(neg)))


def reliability_bins(
    confidence: Sequence[float], success: Sequence[bool], bins: int = CALIBRATION_BINS
) -> list[tuple[int, float, float]]:
    """(results, mean confidence, observed success rate) per equal-width confidence bin of [0, 1] (the last
    bin closed; NaN means in an empty bin)."""
    p = np.asarray(confidence, dtype=np.float64)
    y = np.asarray(success, dtype=bool)
    which = np.minimum((p * bins).astype(int), bins - 1)
    return [(int((which == b).sum()), float(p[which == b].mean()) if (which == b).any() else float("nan"),
             float(y[which == b].mean()) if (which == b).any() else float("nan")) for b in range(bins)]


def expected_calibration_error(
    confidence: Sequence[float], success: Sequence[bool], bins: int = CALIBRATION_BINS
) -> float:
    """Sum over equal-width confidence bins of |success rate - mean confidence| weighted by the bin's share
    of the results (0: calibrated; NaN without results)."""
    cells = reliability_bins(confidence, success, bins)
    total = sum(n for n, _, _ in cells)
    if not total:
        return float("nan")
    return float(sum(n / total * abs(rate - mean) for n, mean, rate in cells if n))


def confident_wrong(
    confidence: Sequence[float], success: Sequence[bool], threshold: float = CONFIDENT
) -> tuple[int, int]:
    """(failed results with confidence >= threshold, results with confidence >= threshold)."""
    p = np.asarray(confidence, dtype=np.float64)
    y = np.asarray(success, dtype=bool)
    return int(((p >= threshold) & ~y).sum()), int((p >= threshold).sum())


def calibration_stats(confidence: Sequence[float], success: Sequence[bool]) -> dict[str, Any]:
    """auc (`roc_auc`, None: one class only), ece, confident_wrong and confident (`confident_wrong` at
    `CONFIDENT`) of some results' confidences and successes (the dataset's success rule)."""
    wrong, confident = confident_wrong(confidence, success)
    return {"auc": roc_auc(confidence, success), "ece": expected_calibration_error(confidence, success),
            "confident_wrong": wrong, "confident": confident}


def _with_confidence(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records with a finite confidence (a GenReg method that did not raise)."""
    return [r for r in records if isinstance(r.get("confidence"), (int, float)) and math.isfinite(r["confidence"])]


def _calibration_cells(c: dict[str, Any] | None) -> str:
    """` AUC | ECE | k of n at >= 0.5 |` of a `calibration_stats` (dashes without one)."""
    if c is None:
        return " – | – | – |"
    return (f" {_f(c['auc'], 3)} | {_f(c['ece'], 3)} | {c['confident_wrong']} of {c['confident']} "
            f"at >= {CONFIDENT:g} |")


def confidence_split(
    scores: Sequence[float], labels: Sequence[bool], threshold: float
) -> dict[str, Any]:
    """Success rate (and count) of the pairs with confidence >= threshold and of those below it."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    above = s >= threshold
    return {
        "threshold": threshold, "n_above": int(above.sum()), "n_below": int((~above).sum()),
        "success_above": float(y[above].mean()) if above.any() else None,
        "success_below": float(y[~above].mean()) if (~above).any() else None,
    }


def confidence_rows(
    run: BenchRun, thresholds: Sequence[float] = DEFAULT_CONFIDENCE_THRESHOLDS
) -> list[dict[str, Any]]:
    """Does `RegistrationResult.confidence` separate successes from failures? Per dataset and pooled per kind.

    Row: dataset, method, pairs, successes, auc (None: one class only), ece, confident_wrong, confident
    (`calibration_stats`), mean_confidence, splits (one `confidence_split` per threshold).
    """
    groups: list[tuple[str, str, list[dict[str, Any]]]] = []
    with_conf = _with_confidence([r for r in run.records if r["method"] in GENREG_METHODS])
    for method in GENREG_METHODS:
        mine = [r for r in with_conf if r["method"] == method]
        for name in run.datasets:
            groups.append((name, method, [r for r in mine if r["dataset"] == name]))
        for kind in ("object", "scene"):
            names = {n for n, d in run.datasets.items() if d["kind"] == kind}
            groups.append((f"all {kind} datasets", method, [r for r in mine if r["dataset"] in names]))
    rows = []
    for name, method, rs in groups:
        if not rs:
            continue
        scores = [r["confidence"] for r in rs]
        labels = [bool(r["success"]) for r in rs]
        rows.append({"dataset": name, "method": method, "pairs": len(rs), "successes": int(sum(labels)),
                     **calibration_stats(scores, labels), "mean_confidence": float(np.mean(scores)),
                     "splits": [confidence_split(scores, labels, t) for t in thresholds]})
    return rows


def _f(x: float | None, digits: int) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _pct(x: float | None) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{100 * x:.0f}%"


CALIBRATION_HEAD = f" conf. AUC | conf. ECE | confident-wrong (conf >= {CONFIDENT:g}) |"


def dataset_table(rows: Sequence[dict[str, Any]], units: str) -> str:
    """Markdown table of `summarize` rows; with `asymmetric` stats, three columns without the symmetric
    categories; with `calibration` stats (GenReg's confidence), its ROC AUC, ECE and confident-wrong count
    (dashes in the rows without confidences)."""
    asym = any("asymmetric" in r for r in rows)
    calib = any("calibration" in r for r in rows)
    head = (f"| method | CD ({units}) | RE mean (deg) | RE median (deg) | TE mean ({units}) | "
            f"TE median ({units}) | success | ms/pair median |"
            + (" RE mean w/o sym. (deg) | TE mean w/o sym. | success w/o sym. |" if asym else "")
            + (CALIBRATION_HEAD if calib else ""))
    lines = [head, "|" + "---|" * (8 + 3 * asym + 3 * calib)]
    for r in rows:
        line = f"{_metric_cells(r)} {_f(r['ms_median'], 1)} |"
        if asym:
            a = r.get("asymmetric")
            line += (f" {_f(a['re_mean'], 2)} | {_f(a['te_mean'], 4)} | {_pct(a['success'])} |" if a
                     else " – | – | – |")
        if calib:
            line += _calibration_cells(r.get("calibration"))
        lines.append(line)
    return "\n".join(lines)


def success_text(rule: dict[str, Any]) -> str:
    """'RE < 5 deg and TE < 0.1' of a stored `datasets.Success` (no TE rule: None or inf in the JSON)."""
    te = rule.get("max_te")
    bounded = te is not None and math.isfinite(te)
    return f"RE < {rule['max_re_deg']:g} deg" + (f" and TE < {te:g}" if bounded else "")


def _metric_cells(r: dict[str, Any], digits: int = 4) -> str:
    """`| method (errors) | CD | RE mean | RE median | TE mean | TE median | success |` of a summary row."""
    err = f" ({r['errors']} errors)" if r["errors"] else ""
    return (f"| {r['method']}{err} | {_f(r['cd'], digits)} | {_f(r['re_mean'], 2)} | {_f(r['re_median'], 2)} | "
            f"{_f(r['te_mean'], digits)} | {_f(r['te_median'], digits)} | {_pct(r['success'])} |")


def ablation_rows(section: dict[str, Any], dataset: str) -> list[dict[str, Any]]:
    """`summarize` rows of one dataset of an ablation section, in the section's row order, plus the mean of
    each of the section's `extras` (record keys; the ground-truth row takes the mean of the dataset's
    `truth` list where the extra names one)."""
    info = section["datasets"][dataset]
    records = [r for r in section["records"] if r["dataset"] == dataset]
    rows = summarize(records, info["cd_floor"])
    for row in rows:
        for extra in _extras(section):
            if row["method"] == "ground truth":
                values = info.get(extra["truth"], []) if "truth" in extra else []
            else:
                values = [r.get(extra["key"], float("nan")) for r in records if r["method"] == row["method"]]
            row[extra["key"]] = _nanstat([float("nan") if v is None else v for v in values], np.mean)
    rank = {name: k for k, name in enumerate(["ground truth", *section.get("order", [])])}
    return sorted(rows, key=lambda r: rank.get(r["method"], len(rank)))


def _extras(section: dict[str, Any]) -> list[dict[str, str]]:
    """Extra table columns of an ablation section (runs written before `extras` existed: inliers)."""
    return section.get("extras") or [
        {"key": "inlier_ratio", "header": "inliers", "format": "pct", "truth": "gt_inlier_ratio"}]


def _extra_cell(value: float | None, fmt: str) -> str:
    return _pct(value) if fmt == "pct" else _f(value, int(fmt[1:]))


def ablation_table(section: dict[str, Any], rows: Sequence[dict[str, Any]], units: str, threads: int) -> str:
    column, extras = section["column"], _extras(section)
    head = (f"| {column} | CD ({units}) | RE mean (deg) | RE median (deg) | TE mean ({units}) | "
            f"TE median ({units}) | success | " + "".join(f"{e['header']} | " for e in extras)
            + f"{column} ms median ({threads} thread{'s' if threads != 1 else ''}) |")
    lines = [head, "|" + "---|" * (8 + len(extras))]
    lines += [f"{_metric_cells(r)} " + "".join(f"{_extra_cell(r.get(e['key']), e['format'])} | " for e in extras)
              + f"{_f(r['ms_median'], 2)} |" for r in rows]
    return "\n".join(lines)


def ablation_markdown(section: dict[str, Any], threads: int) -> list[str]:
    """Lines of one ablation section: title, description, one table per dataset."""
    out = ["", f"## {section['title']}", "", section["description"]]
    for name, info in section["datasets"].items():
        sr = info["success"]
        network = info.get("network_seconds")
        out += [
            "",
            f"### {info['title']}",
            "",
            (f"{info['pairs']} of {info['available_pairs']} pairs, {info['points_per_cloud']} points per source "
             f"cloud, GenReg checkpoint `{info['checkpoint']}` at N = {info['num_points']}, units: {info['units']}; "
             f"success: {success_text(sr)}"
             + (f"; network (shared, not in the solver times) {1e3 * _nanstat(network, np.median):.1f} ms median."
                if network else ".")),
            "",
            ablation_table(section, ablation_rows(section, name), info["units"], threads),
        ]
    return out


def markdown(run: BenchRun, thresholds: Sequence[float] = DEFAULT_CONFIDENCE_THRESHOLDS) -> str:
    m = run.meta
    th = m["threads"]
    ck = m["checkpoints"]
    ablations = m.get("ablations")
    out = [
        f"# GenReg benchmark: suite `{m['suite']}`" + (f", ablations {', '.join(ablations)}" if ablations else ""),
        "",
        f"- Date {m['date']}; {m['machine']['cpu_count']} CPUs; torch {m['machine']['torch']}"
        + (f"; suite wall time {m['wall_seconds']:.0f} s" if "wall_seconds" in m else "")
        + (f"; 1-min load average {m['load_average']['start']:.1f} at start, {m['load_average']['end']:.1f} at end "
           "(other jobs share the CPUs)." if "load_average" in m else "."),
        (f"- **Threads: {th['requested']}** (torch {th['torch']}, OpenMP/Open3D OMP_NUM_THREADS={th['OMP_NUM_THREADS']}"
        f" with OMP_WAIT_POLICY={th['OMP_WAIT_POLICY']}, small_gicp {th['small_gicp']})."),
        (f"- Checkpoints: objects `{ck['object']}`, scenes `{ck['scene']}`. `genreg` = network + PDSAC; "
        "`genreg+icp` = the API's point-to-point ICP refinement after it, with its guard (below confidence "
        "`refine.guard_below`, ICP from identity competes and the more confident result wins)."),
        ("- RE: angle of R_est R_gt^T (deg). TE: |t_est - t_gt| in the dataset's units. CD: mean of the two "
        f"mean nearest-neighbour distances, on at most {m['options']['cd_points']} random points per cloud; "
        "the `ground truth` row is the CD at the true pose (the floor)."),
        ("- Success: RE < 5 deg and TE < 0.1 in the unit box; RE < 2 deg and TE < 0.1 m on real (metric) "
        "frame pairs (TE is taken at the camera origin); RE < 5 deg on the unit sphere (RPM-Net-style pairs); "
        "RE < 2 deg and TE < 0.05 m on kidnapped frame pairs. `identity` is no registration (the motion in the "
        "pairs). `truth+gicp` is given the answer: small_gicp GICP started at the true pose. Where it ends outside "
        "the rule, the clouds' geometry (as GICP weighs it) and the recorded pose disagree by more than the rule "
        "allows: there the rule measures agreement with the recorded poses at the level of their own errors."),
        ("- Overlap share of a pair: the share of source points (at most "
         f"{m['options']['cd_points']} random ones) with a target point within the radius at the true pose: "
         "5 cm on metric frames, 0.05 on the unit sphere (5 % of the radius), 0.025 in the unit box. Means "
         f"'w/o sym.' leave out the symmetric ModelNet40 categories ({', '.join(SYMMETRIC_CATEGORIES)})."),
    ]
    present = {r["method"] for r in run.records}
    notes = {"genreg+p2plane": "`genreg+p2plane` = the same with point-to-plane ICP",
             "genreg+gicp": "`genreg+gicp` = the same with small_gicp's GICP (the node's scene setting)",
             "fpfh+ransac+icp-accurate": ("`fpfh+ransac+icp` on metric frames runs at 5 cm feature voxels (fast), "
                                          "`fpfh+ransac+icp-accurate` at 2.5 cm (normal and FPFH radii and RANSAC "
                                          "distance halved too)"),
             "kiss-matcher+p2plane": ("`kiss-matcher+p2plane` = KISS-Matcher (pip `kiss-matcher`, default gains, "
                                      "voxel `kiss_voxel_size` of the baseline settings: 5 cm on metric frames) then "
                                      "point-to-plane ICP")}
    if present & set(notes):
        out.append("- " + "; ".join(v for k, v in notes.items() if k in present) + ".")
    if run.datasets:
        out.append("- ms/pair: wall time of one registration at batch 1 (median), each method's preprocessing "
                   "(downsampling, normals, features, resampling) included.")
    for msg in run.skipped:
        out.append(f"- **Skipped:** {msg}")
    for name, info in run.datasets.items():
        rs = [r for r in run.records if r["dataset"] == name]
        rows = summarize(rs, info["cd_floor"])
        asym = next((r["asymmetric"]["pairs"] for r in rows if "asymmetric" in r), None)
        out += [
            "",
            f"## {info['title']}",
            "",
            f"{info['pairs']} of {info['available_pairs']} pairs, {info['points_per_cloud']} points per source "
            f"cloud, units: {info['units']}; success: {success_text(info['success'])}; "
            f"GenReg checkpoint `{info['checkpoint']}`" + ("" if info["genreg"] else " (missing: GenReg skipped)")
            + _overlap_text(info) + (f"; {asym} pairs outside the symmetric categories" if asym is not None else "")
            + ".",
            "",
            dataset_table(rows, info["units"]),
        ]
        if varies_in_overlap(info):
            out += ["", f"Success by overlap share (pairs per bin in brackets), `{name}`:", "", overlap_table(rs)]
        if name in PAPER_REPORTED:
            p = PAPER_REPORTED[name]
            out += ["", (f"GenReg paper (CVPR 2022), reported for this setting: CD {p['cd']}, RE {p['re_deg']} deg, "
                        f"TE {p['te']} (its own sampling of the meshes, other N).")]
    if run.throughput:
        out += ["", "## GenReg latency (batch 1) and batched throughput", "",
                ("Network + PDSAC only (`Registrar.estimate`, the API's stage), inputs prepared as in the API; "
                "end-to-end batch-1 times are the ms/pair of the tables above."), "",
                "| datasets | checkpoint | N | batch-1 ms | batch | ms/pair batched | speed-up |",
                "|---|---|---|---|---|---|---|"]
        for t in run.throughput:
            out.append(f"| {t['kind']} | `{t['checkpoint']}` | {t['num_points']} | {t['ms_batch1']:.1f} | {t['batch']} | "
                       f"{t['ms_per_pair_batched']:.1f} | {t['ms_batch1'] / t['ms_per_pair_batched']:.2f}x |")
    conf = confidence_rows(run, thresholds)
    if conf:
        split_head = "".join(f" success if conf >= {t:g} (n) | success if conf < {t:g} (n) |" for t in thresholds)
        out += ["", "## Confidence: does it separate successes from failures?", "",
                ("`RegistrationResult.confidence` is a calibrated probability that the pose is right. ROC AUC "
                 "of the confidence for the dataset's success (1 = perfect, 0.5 = chance, – = only successes or "
                 f"only failures); ECE: expected calibration error ({CALIBRATION_BINS} equal-width bins, "
                 "|success rate - mean confidence| weighted by the bin's share; 0 = calibrated); confident-wrong: "
                 f"failed results with confidence >= {CONFIDENT:g}, of all at >= {CONFIDENT:g}; the success rate "
                 "above and below fixed confidence thresholds."),
                "", (f"Reliability diagram (observed success rate against confidence, {CALIBRATION_BINS} bins, "
                     "GenReg's rows per dataset kind): [reliability.png](reliability.png)"), "",
                "![reliability diagram](reliability.png)", "",
                ("| dataset | method | pairs | successes | mean confidence | ROC AUC | ECE | confident-wrong |"
                 + split_head), "|---" * (8 + 2 * len(thresholds)) + "|"]
        for c in conf:
            splits = "".join(f" {_pct(sp['success_above'])} ({sp['n_above']}) | {_pct(sp['success_below'])} "
                             f"({sp['n_below']}) |" for sp in c["splits"])
            out.append(f"| {c['dataset']} | {c['method']} | {c['pairs']} | {c['successes']} | "
                       f"{c['mean_confidence']:.3f} |" + _calibration_cells(c) + splits)
    for section in run.ablations:
        out += ablation_markdown(section, th["requested"])
    return "\n".join(out) + "\n"


def _overlap_text(info: dict[str, Any]) -> str:
    shares = [v for v in info.get("overlap") or [] if v is not None]
    if not shares:
        return ""
    return (f"; overlap share (within {info['overlap_radius']:g} {info['units']}) mean {np.mean(shares):.2f}, "
            f"range {min(shares):.2f}-{max(shares):.2f}")


def _clean(value: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def to_json(run: BenchRun, thresholds: Sequence[float] = DEFAULT_CONFIDENCE_THRESHOLDS) -> dict[str, Any]:
    summaries = {
        name: summarize([r for r in run.records if r["dataset"] == name], info["cd_floor"])
        for name, info in run.datasets.items()
    }
    ablations = [{**a, "summary": {name: ablation_rows(a, name) for name in a["datasets"]}} for a in run.ablations]
    return _clean({"meta": run.meta, "datasets": run.datasets, "summary": summaries, "skipped": run.skipped,
                   "throughput": run.throughput, "confidence": confidence_rows(run, thresholds),
                   "records": run.records, "ablations": ablations})


def _grid(n: int) -> tuple[Any, list[Any]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(4, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat)


def _colors(methods: Sequence[str]) -> dict[str, Any]:
    import matplotlib.pyplot as plt

    cmap = plt.get_cmap("tab10")
    return {m: cmap(i % 10) for i, m in enumerate(methods)}


def plot_re_cdf(run: BenchRun, path: Path) -> Path:
    """Cumulative distribution of rotation error per method, one panel per dataset (log RE axis)."""

    colors = _colors(method_order(r["method"] for r in run.records))
    fig, axes = _grid(len(run.datasets))
    for ax, (name, info) in zip(axes, run.datasets.items()):
        for m, color in colors.items():
            re = np.sort(np.asarray(
                [r["re_deg"] for r in run.records if r["dataset"] == name and r["method"] == m], dtype=np.float64))
            if len(re) == 0:
                continue
            re = np.where(np.isfinite(re), np.maximum(re, 1e-3), 360.0)  # errors plot as off-scale
            ax.step(re, np.arange(1, len(re) + 1) / len(re), where="post", label=m, color=color,
                    linestyle="--" if m in REFERENCE_METHODS else "-")
        ax.axvline(info["success"]["max_re_deg"], color="grey", linewidth=0.8, linestyle=":")
        ax.set(xscale="log", xlim=(1e-2, 180), ylim=(0, 1), title=name, xlabel="RE (deg)", ylabel="fraction <= RE")
        ax.grid(alpha=0.3)
    return _save_with_legend(fig, axes, path, columns=8)


def _save_with_legend(fig: Any, axes: Sequence[Any], path: Path, columns: int) -> Path:
    """One legend (every panel's lines, each label once; at most `columns` wide and 2.2 inches a column)
    under the panels, then save the figure to `path` and close it."""
    import matplotlib.pyplot as plt

    legend: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
    labels = method_order(legend)
    handles = [legend[label] for label in labels]
    width, height = fig.get_size_inches()
    ncol = max(1, min(len(labels), columns, int(width // 2.2)))
    fig.legend(handles, labels, loc="lower center", ncol=ncol, frameon=False)
    fig.tight_layout(rect=(0, min(0.5, (0.1 + 0.25 * math.ceil(len(labels) / ncol)) / height), 1, 1))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_accuracy_time(run: BenchRun, path: Path) -> Path:
    """Mean rotation error against median ms per pair (both log), one point per method, one panel per dataset."""
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullLocator

    colors = _colors(method_order(r["method"] for r in run.records))
    fig, axes = _grid(len(run.datasets))
    for ax, name in zip(axes, run.datasets):
        for row in summarize([r for r in run.records if r["dataset"] == name]):
            x, y = row["ms_median"], row["re_mean"]
            if row["method"] in REFERENCE_METHODS or not (math.isfinite(x) and math.isfinite(y)) or x <= 0:
                continue
            ax.scatter(x, max(y, 1e-3), color=colors[row["method"]])
            ax.annotate(row["method"], (x, max(y, 1e-3)), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set(xscale="log", yscale="log", title=name, xlabel="ms per pair (median, batch 1)",
               ylabel="mean RE (deg)")
        for axis in (ax.xaxis, ax.yaxis):  # ticks at 1, 2, 5 x 10^k, labelled plainly
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_locator(NullLocator())
        ax.grid(alpha=0.3)
    fig.suptitle(f"Accuracy against time (lower left is better), {run.meta['threads']['requested']} threads")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_success_overlap(run: BenchRun, path: Path) -> Path | None:
    """Success rate against overlap share (OVERLAP_BINS, at bin centres; empty bins skipped), one line per
    method, one panel per dataset whose overlap varies; None when no dataset does."""

    names = [n for n, info in run.datasets.items() if varies_in_overlap(info)]
    if not names:
        return None
    colors = _colors(method_order(r["method"] for r in run.records))
    centres = 0.5 * (np.asarray(OVERLAP_BINS[:-1]) + np.asarray(OVERLAP_BINS[1:]))
    fig, axes = _grid(len(names))
    for ax, name in zip(axes, names):
        for m, cells in success_by_overlap([r for r in run.records if r["dataset"] == name]).items():
            keep = [k for k, (n, _) in enumerate(cells) if n]
            ax.plot(centres[keep], [cells[k][1] for k in keep], marker="o", label=m, color=colors[m],
                    linestyle="--" if m in REFERENCE_METHODS else "-")
        ax.set(xlim=(0, 1), ylim=(-0.02, 1.02), title=name, xlabel="overlap share (bin centre)", ylabel="success rate")
        ax.grid(alpha=0.3)
    return _save_with_legend(fig, axes, path, columns=6)


def plot_reliability(run: BenchRun, path: Path) -> Path | None:
    """Reliability diagram: observed success rate against mean confidence in `CALIBRATION_BINS` equal-width
    bins (empty bins skipped), one line per GenReg method, one panel per dataset kind (object, scene) with
    its pooled results, results per bin beneath; None without confidences."""
    import matplotlib.pyplot as plt

    scored = _with_confidence([r for r in run.records if r["method"] in GENREG_METHODS])
    kinds = [k for k in ("object", "scene")
             if any(run.datasets.get(r["dataset"], {}).get("kind") == k for r in scored)]
    if not kinds:
        return None
    colors = _colors(method_order(r["method"] for r in run.records))
    edges = np.linspace(0, 1, CALIBRATION_BINS + 1)
    fig, axes = plt.subplots(2, len(kinds), figsize=(4.6 * len(kinds), 5.4), height_ratios=(3, 1),
                             squeeze=False, sharex=True)
    for col, kind in enumerate(kinds):
        top, bottom = axes[0, col], axes[1, col]
        top.plot([0, 1], [0, 1], "k:", label="perfectly calibrated")
        mine = [r for r in scored if run.datasets[r["dataset"]]["kind"] == kind]
        methods = method_order(r["method"] for r in mine)
        width = 1 / CALIBRATION_BINS / max(1, len(methods))
        for k, m in enumerate(methods):
            rs = [r for r in mine if r["method"] == m]
            p, y = [r["confidence"] for r in rs], [bool(r["success"]) for r in rs]
            cells = [c for c in reliability_bins(p, y) if c[0]]
            top.plot([c[1] for c in cells], [c[2] for c in cells], "o-", color=colors[m],
                     label=f"{m} (ECE {expected_calibration_error(p, y):.3f})")
            counts = [n for n, _, _ in reliability_bins(p, y)]
            bottom.bar(edges[:-1] + (k + 0.5) * width, counts, width=width, color=colors[m])
        top.set(xlim=(0, 1), ylim=(-0.02, 1.02), ylabel="observed success rate",
                title=f"{kind} datasets ({len(mine)} results)")
        top.legend(loc="best", fontsize=7)
        top.grid(alpha=0.3)
        bottom.set(xlabel="confidence (predicted probability of success)", ylabel="results")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def load_run(path: str | Path) -> BenchRun:
    """A run back from its results.json (None where the run had NaN), e.g. to re-render the report."""
    data = json.loads(Path(path).read_text())
    nan = float("nan")

    def restore(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [{k: (nan if v is None and k in ("re_deg", "te", "cd", "seconds") else v) for k, v in r.items()}
                for r in records]

    ablations = [{**{k: v for k, v in a.items() if k != "summary"}, "records": restore(a["records"])}
                 for a in data.get("ablations", [])]
    return BenchRun(data["meta"], data["datasets"], restore(data["records"]), data["throughput"], data["skipped"],
                    ablations)


def write_report(
    run: BenchRun, out_dir: str | Path, thresholds: Sequence[float] = DEFAULT_CONFIDENCE_THRESHOLDS
) -> dict[str, Path]:
    """Write report.md, results.json and (with method tables) re_cdf.png, accuracy_vs_time.png, when a
    dataset's overlap varies success_vs_overlap.png, and with GenReg confidences reliability.png into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out / "report.md", "json": out / "results.json"}
    paths["markdown"].write_text(markdown(run, thresholds))
    paths["json"].write_text(json.dumps(to_json(run, thresholds), indent=1, allow_nan=False))
    if run.datasets:
        paths["re_cdf"] = plot_re_cdf(run, out / "re_cdf.png")
        paths["accuracy_vs_time"] = plot_accuracy_time(run, out / "accuracy_vs_time.png")
        overlap = plot_success_overlap(run, out / "success_vs_overlap.png")
        if overlap is not None:
            paths["success_vs_overlap"] = overlap
        reliability = plot_reliability(run, out / "reliability.png")
        if reliability is not None:
            paths["reliability"] = reliability
    return paths
