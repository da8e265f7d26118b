"""Inference options for the network stage (encode + interact + generate) of the shipped models at N=512.

    python scripts/bench_network.py --threads 1 2 --pairs 10
    python scripts/bench_network.py --threads 2 --pairs 5 --repeats 2 --models modelnet40

For each shipped model (`modelnet40`, `modelnet40_partial`, `7scenes`) on RPM-Net-style ModelNet40
unseen-category pairs, prepared as the API prepares them (`Registrar.prepare`, float32 (1, 512, 3)), it
times the network stage `model.encode` -> `model.interact` -> `model.generate` with:

- eager under `torch.no_grad()` (the reference) and under `torch.inference_mode()` (as `Registrar.estimate`);
- `torch.compile` (default inductor backend) of a wrapper taking the kNN graph as an input;
- bf16 autocast (`torch.autocast("cpu", dtype=torch.bfloat16)`) around the eager stages;
- ONNX Runtime (CPU execution provider, intra-op threads = the thread count, no spinning) on the same
  wrapper exported with `torch.onnx.export` (dynamo exporter, the legacy one if that fails).

The kNN graph is built outside torch (`gcnn.knn_indices`, a compiled kernel, on the centred clouds, exactly
as `encode` builds it); the compiled and ONNX options get it as an input, and their times include that
query and every numpy <-> torch conversion, so each time covers the same work: float32 (1, 512, 3) torch
tensors in, torch outputs out. Eager `encode` builds the graph itself. Eager inference also runs the
encoder's other compiled kernels (`genreg_core.kernels`); traced and compiled graphs keep the torch forms.

Method: one subprocess per thread count (`genreg_bench.cli.configure_threads` before torch loads,
`retain_freed_memory`); the ONNX files are exported once, in a subprocess of their own, before them.
Each option runs once on every pair for accuracy (also its warm-up, with one more warm-up call), then the
timed calls are interleaved: per repeat and pair every option runs once, in a rotating order (bf16
autocast, ~8x slower than eager on a CPU without native bf16, only in the first --bf16-repeats repeats:
its ratios pair it with the reference calls of those repeats). The table gives the median ms, the median
of the paired ratios option / eager no_grad (same repeat and pair, run back to back) and the share of
those pairs in which the option was faster; the largest absolute difference to the eager float32
reference over the pairs of source_generated / target_generated, of the match log-weights (both
directions), of the weights themselves (exp, for information) and of the overlap logits (models with an
overlap head); and the share of identical argmax picks. An option passes when the differences of the
generated clouds, log-weights and overlap logits are all <= 1e-4.

The first run on a machine compiles (inductor: about 80 s per model and thread count on the loaded
2-core machine, then cached under /tmp/torchinductor_$USER: a few s); the ONNX export takes ~25 s per
model (plus one plain export). --options selects a subset (the reference always runs).

ONNX Runtime's CPU provider has no float64 Acos kernel, which `invariant.smallest_eigenpair3` uses; the
script checks that on the plain export and then exports with torch.acos on float64 replaced by an exact
float64 decomposition (a float32 asin seed of the half angle and two float64 Newton steps, equal to
torch.acos to ~1e-15; `acos_float64`) during the export only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

if TYPE_CHECKING:
    import torch
    from torch import nn

MODELS = ("modelnet40", "modelnet40_partial", "7scenes")
NUM_POINTS = 512
TOLERANCE = 1e-4
REFERENCE = "eager no_grad"
OPTIONS = (REFERENCE, "eager inference_mode", "torch.compile (inductor)", "bf16 autocast", "onnxruntime")
OUTPUTS = ("source_generated", "target_generated", "log_w_a", "log_w_b", "best_a", "best_b",
           "overlap_a", "overlap_b")  # the network outputs compared, in the order every runner returns them
Outputs = tuple["torch.Tensor | None", ...]
Runner = Callable[["torch.Tensor", "torch.Tensor"], Outputs]
Figures = dict[str, Any]


def onnxruntime_version() -> str | None:
    """The installed onnxruntime's version, or None: it is optional (`pip install onnxruntime onnx
    onnxscript`; scripts/setup.sh does not install it, the product does not use it)."""
    try:
        import onnxruntime
    except ImportError:
        return None
    return onnxruntime.__version__


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts, one subprocess each")
    p.add_argument("--pairs", type=int, default=10, help="ModelNet40 pairs (evenly spread over the test set)")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per option and pair (median over all)")
    p.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    available = [o for o in OPTIONS[1:] if o != "onnxruntime" or onnxruntime_version()]
    p.add_argument("--options", nargs="+", default=available, choices=OPTIONS[1:],
                   help="options beside the reference (eager no_grad, always run); default all (onnxruntime "
                   "if installed)")
    p.add_argument("--bf16-repeats", type=int, default=1,
                   help="repeats in which bf16 autocast is timed too (it is ~8x slower without native bf16)")
    p.add_argument("--json", help="also write every figure to this JSON file")
    p.add_argument("--worker-out", help=argparse.SUPPRESS)  # internal: measure one thread count, write JSON
    p.add_argument("--export-dir", help=argparse.SUPPRESS)  # internal: ONNX files (and export.json) live here
    p.add_argument("--export-only", action="store_true", help=argparse.SUPPRESS)  # internal: export, then exit
    return p.parse_args(argv)


def one_line(exc: BaseException) -> str:
    """The first non-empty line of an exception, with its type."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"[:200]


# --- the network with the kNN graph as an input ------------------------------------------------------------

def make_core(model: nn.Module) -> nn.Module:
    """`GenRegNet.encode` / `interact` / `generate` as one module taking the kNN graph (`GenRegNet.knn_graph`)
    as an input: (a, b, graph) -> the OUTPUTS tuple (the overlap logits only for models with an overlap
    head)."""
    import torch

    class NetworkCore(torch.nn.Module):
        def __init__(self, net: nn.Module) -> None:
            super().__init__()
            self.net = net

        def forward(self, a: torch.Tensor, b: torch.Tensor, graph: torch.Tensor) -> tuple[torch.Tensor, ...]:
            enc = self.net.encode(a, b, graph)
            match = self.net.interact(enc)
            out = self.net.generate(enc, match)
            result = (out.source_generated, out.target_generated, match.log_w_a, match.log_w_b, match.best_a,
                      match.best_b)
            if match.overlap_a is None:
                return result
            return (*result, match.overlap_a, match.overlap_b)

    return NetworkCore(model).eval()


def padded(outputs: Sequence[torch.Tensor | None]) -> Outputs:
    """Outputs filled up to len(OUTPUTS) with None (no overlap head)."""
    return (*outputs, *([None] * (len(OUTPUTS) - len(outputs))))


def eager_outputs(model: nn.Module, a: torch.Tensor, b: torch.Tensor) -> Outputs:
    """The network stage as `Registrar.estimate` runs it, outputs in OUTPUTS order."""
    enc = model.encode(a, b)
    match = model.interact(enc)
    out = model.generate(enc, match)
    return (out.source_generated, out.target_generated, match.log_w_a, match.log_w_b, match.best_a, match.best_b,
            match.overlap_a, match.overlap_b)


# --- ONNX export (its own subprocess) ----------------------------------------------------------------------

def acos_float64(x: torch.Tensor) -> torch.Tensor:
    """torch.acos of float64 x in [-1, 1] from ops onnxruntime's CPU provider has in float64 (Sqrt, Sin, Cos,
    Where; Asin in float32 for the seed): acos(|x|) = 2 h with sin h = sqrt((1 - |x|) / 2), h in [0, pi/4]
    (well conditioned), two Newton steps from the float32 asin; acos(x) = pi - acos(-x) for x < 0.
    Equal to torch.acos to ~1e-15 (checked over [-1, 1] and near +-1)."""
    import torch

    s = ((1 - x.abs()) * 0.5).clamp_min(0).sqrt()
    h = torch.asin(s.float()).double()
    for _ in range(2):
        h = h - (torch.sin(h) - s) / torch.cos(h)
    return torch.where(x < 0, math.pi - 2 * h, 2 * h)


@contextlib.contextmanager
def float64_acos_for_onnx() -> Iterator[None]:
    """While exporting: torch.acos on float64 tensors -> `acos_float64` (other dtypes unchanged)."""
    import torch

    original = torch.acos

    def acos(x: torch.Tensor, *args: Any, **kwargs: Any) -> torch.Tensor:
        return acos_float64(x) if x.dtype == torch.float64 and not args and not kwargs else original(x, *args, **kwargs)

    torch.acos = acos
    try:
        yield
    finally:
        torch.acos = original


def ort_inference(path: str | os.PathLike, threads: int) -> Any:
    """An onnxruntime CPU InferenceSession with `threads` intra-op threads (sequential). onnxruntime's idle
    intra-op threads spin by default, unlike torch under OMP_WAIT_POLICY=PASSIVE: on a shared machine compare
    the runners at one thread."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def export_onnx(core: nn.Module, example: tuple[torch.Tensor, ...], path: Path) -> tuple[str, str | None]:
    """Export `core` to `path`: the dynamo exporter, else the legacy one. (exporter used, dynamo error)."""
    import torch

    with torch.no_grad():  # the inference branches (is_grad_enabled() False), as the API runs them
        names = {"input_names": ["a", "b", "graph"], "output_names": list(OUTPUTS[:len(core(*example))])}
        try:
            torch.onnx.export(core, example, str(path), dynamo=True, verbose=False, **names)
            return "dynamo", None
        except Exception as exc:  # noqa: BLE001 - any exporter failure: report it, try the legacy exporter
            dynamo_error = one_line(exc)
        torch.onnx.export(core, example, str(path), dynamo=False, opset_version=18, **names)
        return "legacy (dynamo=False)", dynamo_error


def export_all(args: argparse.Namespace) -> Figures:
    """Export every model's core (example: the first prepared pair) to args.export_dir: once plainly for the
    first model to see whether onnxruntime can load it, then with `float64_acos_for_onnx` if it cannot."""
    from genreg_core.checkpoint import load_checkpoint

    out = Path(args.export_dir)
    pairs = load_pairs(1)
    status: Figures = {"models": {}}
    patched = False
    for n, name in enumerate(args.models):
        model, _ = load_checkpoint(name, num_points=NUM_POINTS)
        core = make_core(model)
        a, b = prepared_inputs(model, pairs)[0]
        example = (a, b, model.knn_graph(a, b))
        entry: Figures = {}
        try:
            if n == 0:  # the plain export: does onnxruntime run it?
                t0 = time.perf_counter()
                entry["exporter"], entry["dynamo_error"] = export_onnx(core, example, out / f"{name}.onnx")
                entry["export_s"] = time.perf_counter() - t0
                try:
                    ort_inference(out / f"{name}.onnx", 1)
                except Exception as exc:  # noqa: BLE001 - unsupported kernels surface here
                    status["plain_error"] = f"{name}: {one_line(exc)}"
                    patched = True
            if n > 0 or patched:
                t0 = time.perf_counter()
                with float64_acos_for_onnx() if patched else contextlib.nullcontext():
                    entry["exporter"], entry["dynamo_error"] = export_onnx(core, example, out / f"{name}.onnx")
                entry["export_s"] = time.perf_counter() - t0
            entry["patched_acos"] = patched
            entry["path"] = str(out / f"{name}.onnx")
        except Exception as exc:  # noqa: BLE001 - both exporters failed: the row reports why
            entry["error"] = f"export failed: {one_line(exc)}"
        status["models"][name] = entry
        print(f"exported {name}: {entry}", file=sys.stderr)
    return status


# --- measuring (worker process) ----------------------------------------------------------------------------

def load_pairs(count: int) -> list[tuple[Any, Any]]:
    """`count` RPM-Net-style ModelNet40 unseen pairs (source, target), evenly spread over the test set."""
    import numpy as np

    from genreg_bench.datasets import RPMNetPairs
    from genreg_core.data import load_modelnet40

    dataset = RPMNetPairs(load_modelnet40("test", "unseen"), seed=0)
    indices = np.linspace(0, len(dataset) - 1, count).astype(int).tolist()
    return [(dataset[i]["source"], dataset[i]["target"]) for i in indices]


def prepared_inputs(model: nn.Module, pairs: Sequence[tuple[Any, Any]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Each pair as the API feeds the network: `Registrar.prepare`, float32 (1, N, 3) tensors a, b."""
    import torch

    from genreg_core.registration import Registrar

    registrar = Registrar(model)
    prepared = [registrar.prepare(source, target) for source, target in pairs]
    return [(torch.from_numpy(p.a[None]), torch.from_numpy(p.b[None])) for p in prepared]


def build_runners(model: nn.Module, threads: int, onnx: Figures | None, options: Sequence[str]
                  ) -> tuple[dict[str, Runner], dict[str, str]]:
    """A callable per selected option (float32 (1, N, 3) a, b -> outputs in OUTPUTS order; the reference
    always) and a note per option (setup figures or why it is missing)."""
    import torch

    core = make_core(model)
    runners: dict[str, Runner] = {}
    notes: dict[str, str] = {}

    def eager(a: torch.Tensor, b: torch.Tensor) -> Outputs:
        with torch.no_grad():
            return eager_outputs(model, a, b)

    def inference(a: torch.Tensor, b: torch.Tensor) -> Outputs:
        with torch.inference_mode():
            return eager_outputs(model, a, b)

    def bf16(a: torch.Tensor, b: torch.Tensor) -> Outputs:
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            return eager_outputs(model, a, b)

    runners[REFERENCE], runners["eager inference_mode"] = eager, inference
    compiled = torch.compile(core)  # lazy: compiles on the first call

    def compiled_run(a: torch.Tensor, b: torch.Tensor) -> Outputs:
        with torch.no_grad():
            return padded(compiled(a, b, model.knn_graph(a, b)))

    runners["torch.compile (inductor)"] = compiled_run
    runners["bf16 autocast"] = bf16
    for option in list(runners):
        if option != REFERENCE and option not in options:
            del runners[option]
    if "onnxruntime" not in options:
        return runners, notes
    if onnx is None or "error" in onnx:
        notes["onnxruntime"] = (onnx or {}).get("error", "not exported")
        return runners, notes
    try:
        inference = ort_inference(onnx["path"], threads)
    except Exception as exc:  # noqa: BLE001 - an unsupported kernel: the row reports it
        notes["onnxruntime"] = f"loading failed: {one_line(exc)}"
        return runners, notes
    inputs = [i.name for i in inference.get_inputs()]

    def ort_run(a: torch.Tensor, b: torch.Tensor) -> Outputs:
        graph = model.knn_graph(a, b)
        feed = dict(zip(inputs, (a.numpy(), b.numpy(), graph.numpy()), strict=True))
        return padded([torch.from_numpy(x) for x in inference.run(None, feed)])

    runners["onnxruntime"] = ort_run
    notes["onnxruntime"] = (f"{onnx['exporter']} export {onnx['export_s']:.0f} s"
                            + ("; float64 acos decomposed" if onnx.get("patched_acos") else ""))
    return runners, notes


def differences(ref: Outputs, out: Outputs) -> dict[str, float]:
    """Largest |out - ref| of the generated clouds, the log-weights, the weights (their exp) and the overlap
    logits (NaN without an overlap head), the share of identical argmax picks and the smallest reference
    log-weight."""
    def largest(*index: int) -> float:
        values = [float((out[i].double() - ref[i].double()).abs().max()) for i in index if ref[i] is not None]
        return max(values) if values else math.nan

    same = sum(int((out[i] == ref[i]).sum()) for i in (4, 5))
    weights = max(float((out[i].double().exp() - ref[i].double().exp()).abs().max()) for i in (2, 3))
    return {"generated": largest(0, 1), "log_w": largest(2, 3), "weights": weights, "overlap": largest(6, 7),
            "same_picks": same / (ref[4].numel() + ref[5].numel()),
            "log_w_min": min(float(ref[i].min()) for i in (2, 3))}


def measure_model(name: str, pairs: Sequence[tuple[Any, Any]], threads: int, args: argparse.Namespace,
                  onnx: Figures | None) -> Figures:
    """Every option on one model: accuracy against the eager float32 reference, then interleaved timing
    (bf16 autocast, about 8x slower than eager without native bf16 on the CPU, only in the first
    args.bf16_repeats repeats)."""
    import torch

    from genreg_core.checkpoint import load_checkpoint

    model, _ = load_checkpoint(name, num_points=NUM_POINTS)
    inputs = prepared_inputs(model, pairs)
    runners, notes = build_runners(model, threads, onnx, args.options)
    dtype = str(next(model.parameters()).dtype).replace("torch.", "")
    reference = [runners[REFERENCE](a, b) for a, b in inputs]
    accuracy: dict[str, list[dict[str, float]]] = {}
    for option in list(runners):
        t0 = time.perf_counter()
        try:
            runners[option](*inputs[0])  # warm-up (compiles, for torch.compile)
        except Exception as exc:  # noqa: BLE001 - e.g. no C++ compiler, an inductor error: the row reports it
            notes[option] = f"failed: {one_line(exc)}"
            del runners[option]
            continue
        if option == "torch.compile (inductor)":
            notes[option] = f"first call (compile) {time.perf_counter() - t0:.0f} s"
        accuracy[option] = [differences(ref, runners[option](a, b)) for ref, (a, b) in zip(reference, inputs,
                                                                                           strict=True)]
    times: dict[str, dict[int, float]] = {option: {} for option in runners}  # by call: (repeat, pair)
    for repeat in range(args.repeats):
        names = [o for o in runners if o != "bf16 autocast" or repeat < args.bf16_repeats]
        for i, (a, b) in enumerate(inputs):
            call = repeat * len(inputs) + i
            shift = call % len(names)
            for option in names[shift:] + names[:shift]:  # rotating order: no option always runs first
                t0 = time.perf_counter()
                runners[option](a, b)
                times[option][call] = time.perf_counter() - t0
    notes[REFERENCE] = f"reference log-w >= {min(d['log_w_min'] for d in accuracy[REFERENCE]):.0f}"
    if "bf16 autocast" in times:
        notes["bf16 autocast"] = f"{len(times['bf16 autocast'])} timed calls"
    rows = {}
    for option in OPTIONS:
        row: Figures = {"note": notes.get(option, "")}
        if option in times:
            ratios = [t / times[REFERENCE][call] for call, t in times[option].items()]
            acc = accuracy[option]
            row.update({
                "ms": 1e3 * statistics.median(times[option].values()), "ratio": statistics.median(ratios),
                "wins": sum(r < 1 for r in ratios) / len(ratios), "calls": len(ratios),
                **{key: max(d[key] for d in acc) for key in ("generated", "log_w", "weights", "overlap")},
                "same_picks": statistics.fmean(d["same_picks"] for d in acc),
            })
            row["passes"] = all(row[key] <= TOLERANCE for key in ("generated", "log_w", "overlap")
                                if not math.isnan(row[key]))
        elif option not in notes:
            continue  # not selected
        rows[option] = row
    return {"dtype": dtype, "torch_threads": torch.get_num_threads(), "rows": rows, "samples": len(times[REFERENCE])}


def measure(args: argparse.Namespace) -> Figures:
    """Every model at one thread count (this process's only one)."""
    threads = args.threads[0]
    from genreg_bench.cli import configure_threads

    configure_threads(threads)  # before torch runs anything
    from genreg_core.memory import retain_freed_memory

    retain_freed_memory()
    load = os.getloadavg()[0]
    status = Path(args.export_dir or ".") / "export.json"
    onnx = json.loads(status.read_text())["models"] if args.export_dir and status.is_file() else {}
    pairs = load_pairs(args.pairs)
    figures: Figures = {"models": {}, "pairs": len(pairs)}
    for name in args.models:
        figures["models"][name] = measure_model(name, pairs, threads, args, onnx.get(name))
        print(f"{threads} thread(s): {name} done", file=sys.stderr)
    figures["load_average"] = [load, os.getloadavg()[0]]
    figures["env"] = {var: os.environ.get(var) for var in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    return figures


def run_subprocess(options: Sequence[str]) -> None:
    subprocess.run([sys.executable, __file__, *options], check=True)


def run_all(args: argparse.Namespace, export_dir: Path) -> tuple[Figures, dict[int, Figures]]:
    """The export subprocess (at the largest thread count), then one measuring subprocess per thread count."""
    common = ["--pairs", str(args.pairs), "--repeats", str(args.repeats), "--models", *args.models,
              "--options", *args.options, "--bf16-repeats", str(args.bf16_repeats), "--export-dir", str(export_dir)]
    export: Figures = {"models": {}}
    if "onnxruntime" in args.options:
        run_subprocess([*common, "--threads", str(max(args.threads)), "--export-only"])
        export = json.loads((export_dir / "export.json").read_text())
    results = {}
    for threads in args.threads:
        out = export_dir / f"figures_{threads}.json"
        run_subprocess([*common, "--threads", str(threads), "--worker-out", str(out)])
        results[threads] = json.loads(out.read_text())
    return export, results


# --- reporting (parent process) ----------------------------------------------------------------------------

def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(str(v) for v in row) + " |" for row in rows])


def diff(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.1e}"


def report(export: Figures, results: dict[int, Figures], load_start: float) -> None:
    import torch

    first = next(iter(results.values()))
    dtypes = sorted({m["dtype"] for r in results.values() for m in r["models"].values()})
    samples = first["models"][next(iter(first["models"]))]["samples"]
    settings = ", ".join(f"{t}: torch {next(iter(r['models'].values()))['torch_threads']} threads, "
                         f"OMP_WAIT_POLICY={r['env']['OMP_WAIT_POLICY']}" for t, r in results.items())
    print(f"Network stage (encode + interact + generate), N={NUM_POINTS}, {first['pairs']} RPM-Net-style ModelNet40 "
          f"unseen pairs prepared by `Registrar.prepare`, float32 inputs, loaded models {'/'.join(dtypes)} "
          f"(fp16 on disk); {samples} interleaved timed calls per option (bf16: see its note); torch {torch.__version__}, onnxruntime "
          f"{onnxruntime_version() or 'not installed'}; one subprocess per thread count ({settings}); "
          f"machine shared with other jobs: 1-min load average {load_start:.2f} at the start, "
          f"{os.getloadavg()[0]:.2f} at the end, on {os.cpu_count()} CPUs.\n")
    rows = []
    for name in next(iter(results.values()))["models"]:
        for threads, figures in results.items():
            for option, row in figures["models"][name]["rows"].items():
                if "ms" not in row:
                    rows.append([name, threads, option, *["-"] * 8, "no", row["note"]])
                    continue
                reference = option == REFERENCE
                rows.append([name, threads, option, f"{row['ms']:.1f}", "1" if reference else f"{row['ratio']:.2f}",
                             "-" if reference else f"{100 * row['wins']:.0f} %", diff(row["generated"]),
                             diff(row["log_w"]), diff(row["weights"]), diff(row["overlap"]), f"{100 * row['same_picks']:.2f} %",
                             "yes" if row["passes"] else "no", row["note"]])
    print(table(["model", "thr", "option", "median ms", "x eager (paired)", "faster in", "max d generated",
                 "max d log-w", "max d weights", "max d overlap", "same picks", f"passes (<= {TOLERANCE:g})",
                 "note"], rows))
    print("\nx eager: median over the timed calls of option / eager no_grad on the same pair, run back to back; "
          "faster in: share of those calls in which the option was faster. Every time includes the scipy kNN "
          "graph and any numpy <-> torch conversion. max d: largest absolute difference to eager no_grad float32 "
          "over the pairs (generated: source_generated and target_generated; log-w: match log-weights both ways; "
          "weights: their exp, for information, not in the pass criterion; overlap: overlap logits); same picks: "
          "share of identical argmax picks (both ways).")
    if "plain_error" in export:
        print(f"Plain ONNX export, onnxruntime: {export['plain_error']} (invariant.smallest_eigenpair3 takes "
              "acos of float64); the timed model is exported with it decomposed (see the module docstring).")
    for name, entry in export["models"].items():
        if entry.get("dynamo_error"):
            print(f"{name}: dynamo exporter failed ({entry['dynamo_error']}); legacy exporter used.")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.export_only:
        from genreg_bench.cli import configure_threads

        configure_threads(args.threads[0])
        status = export_all(args)
        (Path(args.export_dir) / "export.json").write_text(json.dumps(status))
        return 0
    if args.worker_out:
        Path(args.worker_out).write_text(json.dumps(measure(args)))
        return 0
    load_start = os.getloadavg()[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        export, results = run_all(args, Path(tmp))
    report(export, results, load_start)
    print(f"Total run time {time.perf_counter() - t0:.0f} s.")
    if args.json:
        Path(args.json).write_text(json.dumps({"export": export, **{str(t): r for t, r in results.items()}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
