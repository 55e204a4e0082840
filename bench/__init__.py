"""Benchmarks: each ``bench_<area>.py`` has ``main()`` and reports ratios to an in-run baseline."""
