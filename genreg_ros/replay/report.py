"""The replay's outputs: the summary table (printed by genreg-replay and the main job) and the report
folder (report.md, errors.png, trajectory.png). Figures come from `genreg_ros.replay.scoring`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from genreg_ros.replay.scoring import PairResult


def format_summary(s: dict[str, Any], title: str) -> str:
    """The summary table printed by genreg-replay and the main job."""
    def pair(a: dict, b: dict, scale: float, fmt: str) -> str:
        left = f"{a['mean'] * scale:{fmt}} / {a['median'] * scale:{fmt}}"
        right = f"{b['mean'] * scale:{fmt}} / {b['median'] * scale:{fmt}}" if b["n"] else "-"
        return f"{left:<22}{right}"

    reasons = ", ".join(f"{r} {n}" for r, n in s["reasons"].items()) or "none"
    lat = s["latency"]
    lines = [
        title,
        f"pairs              {s['pairs']}: {s['registered']} registered, {s['missing']} without output",
        f"drops              {reasons}",
        f"                   {'GenReg node':<22}Open3D ICP (same pairs)",
        f"RE mean / median   {pair(s['re'], s['icp_re'], 1.0, '.3f')}  deg",
        f"TE mean / median   {pair(s['te'], s['icp_te'], 1e3, '.2f')}  mm",
        f"latency p50 / p95  {lat['median'] * 1e3:.0f} / {lat['p95'] * 1e3:.0f} ms"
        + (f"{'':<10}ICP {s['icp_seconds']['median'] * 1e3:.0f} ms per pair" if s["icp_seconds"]["n"] else ""),
        (f"stamps and frames  {'ok' if not s['header_problems'] else str(s['header_problems']) + ' outputs wrong'}"
        f" ({s['registered']} outputs checked)"),
    ]
    if s["malformed"]:
        kinds: dict[str, int] = {}
        for m in s["malformed"]:
            kinds[m["reason"]] = kinds.get(m["reason"], 0) + 1
        counted = {r: s["node_counts"].get(f"dropped.{r}", 0) for r in kinds}
        lines.append(f"malformed in bag   {len(s['malformed'])} clouds ({_kv(kinds)}); node dropped {_kv(counted)}")
    return "\n".join(lines)


def _kv(d: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in d.items())


# ----------------------------------------------------------------------------- trajectory and report
def chain(pairs: list[PairResult], gap: int, start_pose: np.ndarray, which: str) -> tuple[np.ndarray, int]:
    """Camera positions chained along the pairs k = gap, 2 gap, ... of one bag: T_w_k = T_w_{k-g} T_est.

    which: 'est' (node), 'icp' or 'gt'. A missing estimate holds the pose (identity link). Returns
    ((L+1, 3) positions in the world frame, number of held links)."""
    by_k = {p.k: p for p in pairs}
    T = np.asarray(start_pose, dtype=np.float64)
    positions, held = [T[:3, 3].copy()], 0
    k = gap
    while k in by_k:
        p = by_k[k]
        link = {"est": p.T_est, "icp": p.icp_T, "gt": p.T_gt}[which]
        if link is None:
            held += 1
            link = np.eye(4)
        T = T @ link
        positions.append(T[:3, 3].copy())
        k += gap
    return np.asarray(positions), held


def write_report(
    out_dir: Path, summary: dict[str, Any], pairs: list[PairResult], text: str, gap: int,
    start_poses: dict[str, np.ndarray], settings: dict[str, Any],
) -> Path:
    """report.md, errors.png (RE, TE, latency over the sequence) and trajectory.png in out_dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    x = np.arange(len(pairs))
    err = np.array([p.errors(p.T_est) for p in pairs]).reshape(-1, 2)
    icp = np.array([p.errors(p.icp_T) for p in pairs]).reshape(-1, 2)
    lat = np.array([np.nan if p.latency is None else p.latency * 1e3 for p in pairs])
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for ax, col, label in ((axes[0], 0, "RE [deg]"), (axes[1], 1, "TE [mm]")):
        scale = 1e3 if col == 1 else 1.0
        ax.plot(x, icp[:, col] * scale, ".", color="tab:gray", label="Open3D ICP (p2p)")
        ax.plot(x, err[:, col] * scale, "o", ms=4, color="tab:red", label="GenReg node")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[2].plot(x, lat, "o", ms=4, color="tab:blue")
    missing = [i for i, p in enumerate(pairs) if not p.registered]
    if missing:
        axes[2].plot(missing, np.zeros(len(missing)), "x", color="black", label="no output")
        axes[2].legend(loc="upper right")
    axes[2].set_ylabel("latency [ms]")
    axes[2].set_xlabel("pair (source cloud index in the replay)")
    axes[2].grid(alpha=0.3)
    fig.suptitle(settings.get("title", "genreg replay"))
    fig.tight_layout()
    fig.savefig(out_dir / "errors.png", dpi=90)
    plt.close(fig)

    bags = list(dict.fromkeys(p.bag for p in pairs))
    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    held_text = []
    for bag in bags:
        sub = [p for p in pairs if p.bag == bag]
        if bag not in start_poses:
            continue
        gt, _ = chain(sub, gap, start_poses[bag], "gt")
        est, held = chain(sub, gap, start_poses[bag], "est")
        ic, _ = chain(sub, gap, start_poses[bag], "icp")
        held_text.append(f"{Path(bag).name}: {held} of {len(est) - 1} links held (no output)")
        for ax, (a, b) in zip(axes, ((0, 1), (0, 2))):
            ax.plot(gt[:, a], gt[:, b], "-", color="black", label="ground truth" if bag == bags[0] else None)
            ax.plot(est[:, a], est[:, b], "-", color="tab:red", label="GenReg (chained)" if bag == bags[0] else None)
            ax.plot(ic[:, a], ic[:, b], "--", color="tab:gray", label="ICP (chained)" if bag == bags[0] else None)
    for ax, (a, b) in zip(axes, ("xy", "xz")):
        ax.set_xlabel(f"{a} [m] (world)")
        ax.set_ylabel(f"{b} [m] (world)")
        ax.axis("equal")
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"camera positions chained every {gap} frame(s); " + "; ".join(held_text))
    fig.tight_layout()
    fig.savefig(out_dir / "trajectory.png", dpi=90)
    plt.close(fig)

    md = ["# genreg replay report", "", "```", text, "```", "", "## Settings", ""]
    md += [f"- {k}: `{v}`" for k, v in settings.items()]
    md += ["", "## Node counters during the replay (from /diagnostics)", ""]
    md += [f"- {k}: {v}" for k, v in summary["node_counts"].items()] or ["- (none)"]
    md += ["", "## Accuracy", "", "| | pairs | RE mean | RE median | RE p95 | TE mean | TE median | TE p95 |",
           "|---|---|---|---|---|---|---|---|"]
    for name, re_key, te_key in (("GenReg node", "re", "te"), ("ICP, same pairs", "icp_re", "icp_te"),
                                 ("ICP, all pairs", "icp_all_re", "icp_all_te"),
                                 ("no motion (identity), same pairs", "identity_re", "identity_te")):
        r, t = summary[re_key], summary[te_key]
        md.append(f"| {name} | {r['n']} | {r['mean']:.3f} deg | {r['median']:.3f} deg | {r['p95']:.3f} deg | "
                  f"{t['mean'] * 1e3:.2f} mm | {t['median'] * 1e3:.2f} mm | {t['p95'] * 1e3:.2f} mm |")
    md += ["", "![errors](errors.png)", "", "![trajectory](trajectory.png)", "", "## Pairs", "",
           "| bag | src frame | tgt frame | outcome | RE deg | TE mm | latency ms | ICP RE | ICP TE mm |",
           "|---|---|---|---|---|---|---|---|---|"]
    for p in pairs:
        re, te = p.errors(p.T_est)
        ire, ite = p.errors(p.icp_T)
        outcome = "registered" if p.registered else p.reason
        if p.header_problems:
            outcome += " (" + "; ".join(p.header_problems) + ")"
        lat_ms = "" if p.latency is None else f"{p.latency * 1e3:.0f}"
        md.append(f"| {Path(p.bag).name} | {p.source_frame} | {p.target_frame} | {outcome} | {re:.3f} | "
                  f"{te * 1e3:.2f} | {lat_ms} | {ire:.3f} | {ite * 1e3:.2f} |")
    path = out_dir / "report.md"
    path.write_text("\n".join(md) + "\n")
    return path
