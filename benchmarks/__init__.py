"""The toolbox: timing benches (bench_*.py) and diagnostics of benchmark runs (replays, breakdowns,
counterfactuals), each a script run by hand from the repository root:

    python -m benchmarks.NAME --help

They import the library (sgjax, envs, eval, train) and, for what several of them share, `benchmarks.common`;
never each other. tests/test_benchmarks.py runs every script's --help.
"""
