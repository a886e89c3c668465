"""Benchmarks behind ``floornav bench``: each module times one subsystem on one CPU and
returns a JSON-ready dict; ``run_all`` joins them into one report."""
