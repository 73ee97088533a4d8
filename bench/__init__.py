"""Benchmarks (`make bench`): each part is a module here writing bench/results/<part>.json."""
