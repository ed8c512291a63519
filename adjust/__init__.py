"""SciPy adjustment stage (bundle blocks, Gauss-Helmert, error propagation): not yet implemented."""
