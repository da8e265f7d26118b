"""Benchmarks: GenReg beside classical baselines on the paper's datasets (`genreg-bench`).

Modules: `baselines` (Open3D / small_gicp methods), `suites` (datasets, methods, the run loop),
`report` (tables, confidence analysis, JSON, plots), `cli` (the command). Importing this package is
cheap: the CLI sets thread counts before torch and Open3D load.
"""
