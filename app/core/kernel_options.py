"""numba options of lightflow's kernels, as ``@nb.njit(..., **NO_CFUNC)``.

Each compiled kernel gets wrappers besides its own code, and each costs a share of
its compilation on a first run (a cold start of ``lightflow demo`` compiles every
kernel): :data:`NO_CFUNC` leaves out the C-callable wrapper (only for first-class
function use, which no caller makes), :data:`INTERNAL` also the Python wrapper (for
helpers that only other kernels call).  Neither changes what a kernel computes.
"""

NO_CFUNC = {"no_cfunc_wrapper": True}
INTERNAL = {"no_cfunc_wrapper": True, "no_cpython_wrapper": True}
