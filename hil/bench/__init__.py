"""Benchmarks: they print JSON and measure their reference in the same run."""
