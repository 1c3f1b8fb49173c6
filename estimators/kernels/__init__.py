"""What every compiled kernel shares: how numba compiles and caches them (`_numba`,
`_kernel_cache`), and the small linear algebra and quaternion kernels (`_linalg`,
`_compiled_linalg`, `_compiled_quaternion`). Kernels here import no estimator."""
