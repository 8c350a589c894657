"""The HIL runtime: command line, validation against the seed papers, benchmarks."""
