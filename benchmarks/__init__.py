"""The benchmarks: scripts that measure the project and write benchmarks/results/ (benchmarks/README.md is the
index). Run each from the repository root as a module, `python -m benchmarks.NAME ...`, so that the
repository's packages and the other benchmarks import without any sys.path edit."""
