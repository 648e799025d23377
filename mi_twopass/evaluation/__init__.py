"""References, error metrics, image I/O and the speed-vs-error harness."""
