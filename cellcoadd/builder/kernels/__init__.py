"""Numerical kernels of the builder (numba, compiled on first use and cached on disk).

Lanczos-3 weights, the warp, the interleaved accumulator, mask-bit spreading, the
counter-based noise generator and the filling of an exposure's input planes. No I/O and
no astropy here: arrays in, arrays out.
"""
