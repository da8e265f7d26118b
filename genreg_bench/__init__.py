"""Benchmarks: GenReg beside classical baselines on the paper's datasets (`genreg-bench`).

Modules: `datasets` (the dataset registry, suites, pair plans and each pair's truth), `baselines`
(Open3D / small_gicp methods), `methods` (GenReg and the baselines as one callable, GenReg throughput),
`runner` (the run loop, `BenchRun`, machine metadata), `ablation` (pose solver, backbone), `report`
(tables, confidence analysis, JSON, plots), `map_suite` (localisation in prior maps: `--suite map`),
`cli` (the command). Importing this package is cheap: the
CLI sets thread counts before torch and Open3D load.
"""
