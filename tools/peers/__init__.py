"""The peer systems that tools/benchmark.py runs (each as a subprocess). See tools/README.md."""
