"""Compiled kernels (numba ``@njit`` only) over struct-of-arrays state. No Python objects per particle."""
