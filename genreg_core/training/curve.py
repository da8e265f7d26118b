"""Plot a training run's learning curve (validation RE against wall time and iterations) from log.csv.

    python -m genreg_core.training.curve runs/modelnet40/log.csv build/curve.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def read_log(path: str | Path) -> list[dict[str, float]]:
    """Rows of log.csv as floats (empty cells dropped)."""
    with Path(path).open() as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]


def validation_rows(rows: list[dict[str, float]]) -> list[dict[str, float]]:
    return [r for r in rows if "val_re_mean" in r]


def plot_curve(rows: list[dict[str, float]], out: str | Path, title: str = "") -> Path:
    val = validation_rows(rows)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    hours = [r["elapsed_s"] / 3600 for r in val]
    for key, label in (("val_re_mean", "RE mean"), ("val_re_median", "RE median")):
        ys = [r[key] for r in val if key in r]
        if ys:
            axes[0].plot(hours[: len(ys)], ys, marker="o", ms=3, label=label)
    axes[0].set_xlabel("wall time (h)")
    axes[0].set_ylabel("validation rotation error (deg)")
    axes[0].legend()
    axes[0].grid(alpha=0.3)
    it = [r["iteration"] for r in rows if "loss" in r]
    axes[1].plot(it, [r["loss"] for r in rows if "loss" in r], lw=0.8)
    axes[1].set_xlabel("iteration")
    axes[1].set_ylabel("generator loss (running)")
    axes[1].set_yscale("log")
    axes[1].grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", help="run folder's log.csv")
    parser.add_argument("out", help="PNG to write")
    args = parser.parse_args(argv)
    rows = read_log(args.log)
    plot_curve(rows, args.out, Path(args.log).parent.name)
    for r in validation_rows(rows):
        print(f"iteration {int(r['iteration']):6d}  {r['elapsed_s'] / 3600:6.2f} h  "
              f"RE mean {r['val_re_mean']:6.2f}  median {r['val_re_median']:6.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
