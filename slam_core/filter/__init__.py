"""DynamicSLAM (Algorithm 2) for many users at once: state, parameters, compiled kernels and their NumPy
reference."""
