/* The CPU kernels of torchgi, float32, one image per call: the filters (box, guided, À-Trous,
 * per-pixel kernels and their gradients),
 * the guided filter's gradients, the Denoiser's guided pipeline, the sampling importance and allocation, the temporal
 * ops; the path tracer is tracer.c.
 *
 * Compiled at first use by torchgi/backends/c_kernels/build.py (gcc/cc, -O3 -march=native,
 * -fopenmp where the compiler has it) and called through ctypes, which releases the GIL; each
 * entry point runs its rows in bands, one per thread (OVER_BANDS, common.h). The maths is
 * exactly that of the torch code (backends/torch_code); only the order of the sums differs (box
 * sums accumulate in double here, so they are more accurate).
 */
#include "common.h"

int torchgi_native_version(void) { return 19; }

float torchgi_exp_neg(float d) { return exp_neg(d); }

int torchgi_openmp(void) {
#if defined(_OPENMP)
    return 1;
#else
    return 0;
#endif
}

/* One translation unit for all the filter, pipeline, sampling and accumulation kernels (a unity
 * build), one op family per file: the pipeline's walks share the guided filter's row routines
 * (static, so inlined where they are called, as in one file). The path tracer (tracer.c) is the
 * library's second translation unit. */
#include "importance.c"
#include "atrous.c"
#include "guided.c"
#include "upsample.c"
#include "pipeline.c"
#include "pyramid.c"
#include "allocate.c"
#include "accumulate.c"
#include "kernels.c"
#include "guided_grad.c"
