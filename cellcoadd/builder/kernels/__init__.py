"""Numerical kernels of the builder (numba, compiled on first use and cached on disk).

The descriptor of the resampling kernel (name, half-width, taps: what footprints and
margins read), Lanczos-3 weights, the warp, the interleaved accumulator and the plain
reference it is tested against bit for bit, mask-bit spreading, the counter-based noise
generator, the filling of an exposure's input planes and the interpolation of the pixel
mapping from its grid nodes. Every compiled (numba) function of the package is here. No
I/O and no astropy: arrays in, arrays out.
"""
