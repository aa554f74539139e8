"""fwdfit's benchmarks: ``python -m benchmarks [--quick] [NAME ...]`` regenerates their results."""
