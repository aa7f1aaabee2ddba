/*
 * Optional compiled kernel of converters.cloud_slices: height slices of an unstructured
 * PointCloud2 (any field layout), fusion and decoding in one call. Results are bit-identical to
 * the numpy reference converters.cloud_slices._fuse_numpy (the rules are in the docstring of
 * converters/cloud_slices.py; this file only evaluates them).
 *
 * One pass over the points, in blocks of LCS_BLOCK points of one row:
 *   1. scan: the points whose target-frame height lies in the hull of the bands (from z alone
 *      for an upright target: m[6] == m[7] == 0; a NaN height is never inside), as their
 *      column in the block (branch-free compaction). With AVX2, packed 16-byte points with a
 *      float32 z (x, y, z, intensity: the usual driver layout) upright: eight points from four
 *      contiguous loads against float32 bounds widened beyond any rounding (a superset of the
 *      hull: every band is tested exactly later), compacted by a permutation from a table;
 *   2. take: their x, y, z read and transformed once (float64, R @ p + t evaluated as
 *      ((m0*x + m1*y) + m2*z) + t, as the reference) into buffers of up to LCS_CAP points; a
 *      point with a non-finite coordinate gets a NaN height (inside no band). With AVX2 and
 *      float32 fields, eight points per step from gathers. When the buffers are full:
 *   3. bins: per distinct grid, the bin of every buffered point from an odd polynomial of atan
 *      (error < EPS = 1e-7 rad; a loop the compiler vectorises): exact whenever the approximate
 *      angle is more than 2 * EPS from every bin edge (and a sector's wrap point), else (about
 *      4e-7 / increment of the points, and the origin) from libm's atan2 with the reference's
 *      formula;
 *   4. planar range rho = sqrt(x*x + y*y) and its float32 code (beyond float32: +Inf);
 *   5. per slice: the buffered points inside its band (branch-free compaction; with AVX2 by
 *      permutation), then the minimum of code << 32 | point index in the reduction array
 *      (branch-free store; the order of the points does not matter);
 *   6. decoding: published ranges and the winners' intensities (any element type, cast to
 *      float32 as numpy's astype).
 * The arithmetic has no fused multiply-add and no reassociation (-ffp-contract=off, never
 * -ffast-math), so the scalar build and the AVX2 build (the same C compiled twice, plus the
 * AVX2 functions below, which compute the same formulas lane by lane) give the same bits;
 * `simd = 0` forces the scalar one (tests run both). A gather-based AVX2 scan of any float32
 * layout was no faster than the scalar loop here and was dropped (bench/README.md). The Python
 * module part is empty: converters/_kernels/cloud_slices.py loads this shared object with
 * ctypes; lcs_slices() is called with the GIL released.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Bump with any change of lcs_plan or of a function's signature or semantics. */
#define LCS_ABI 1

#define LCS_EMPTY INT64_MAX
#define LCS_CODE_NEG_INF 0x7F800000LL
#define LCS_CODE_POS_INF 0x7F800001LL
#define LCS_BLOCK 1024 /* points scanned per block (inside one row) */
#define LCS_CAP 4096   /* candidates buffered before they are fused (>= 2 * LCS_BLOCK) */
#define LCS_EPS 1e-7   /* bound on |lcs_atan2_approx - atan2| (tests check the polynomial) */
#define LCS_PI 3.141592653589793
#define LCS_TWO_PI (2.0 * LCS_PI)

#if defined(_WIN32)
#define LCS_EXPORT __declspec(dllexport)
#else
#define LCS_EXPORT __attribute__((visibility("default")))
#endif

#if defined(__GNUC__) || defined(__clang__)
#define LCS_INLINE static inline __attribute__((always_inline))
#else
#define LCS_INLINE static inline
#endif

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define LCS_AVX2 1
#include <immintrin.h>
#define LCS_TARGET __attribute__((target("avx2")))
#else
#define LCS_AVX2 0
#endif

/* Element types (converters/_kernels/_loader.py TYPE_CODES), native byte order. */
enum { LCS_F32, LCS_F64, LCS_U8, LCS_U16, LCS_U32, LCS_I8, LCS_I16, LCS_I32 };

/* Everything but the cloud: built once per converter by cloud_slices.py (a ctypes Structure with
 * the same fields in the same order). S slices, G distinct grids. */
typedef struct {
    int64_t n_slices, n_grids;
    const double *m;                     /* (12) rotation row-major, then translation */
    const double *zlo, *zhi;             /* (S) band, target frame, inclusive */
    const double *rlo, *rhi;             /* (S) planar range limits, inclusive */
    const int64_t *sgrid, *soff;         /* (S) grid index, first bin in the reduction array */
    const float *inf_value, *fill_value; /* (S) decoded +Inf and empty-bin values */
    const double *gmin, *ginc, *ginv;    /* (G) angle_min, increment, 1 / increment */
    const int64_t *gsize, *gfull;        /* (G) bins, full circle */
    double zall_lo, zall_hi;             /* hull of the bands */
    int64_t size;                        /* bins of all slices */
} lcs_plan;

LCS_EXPORT int32_t lcs_abi(void) { return LCS_ABI; }
LCS_EXPORT int64_t lcs_plan_size(void) { return (int64_t)sizeof(lcs_plan); }

/* Buffers of one call (one malloc). */
typedef struct {
    double *x, *y, *z, *rho; /* (CAP) target-frame coordinates, planar range */
    int64_t *key;            /* (CAP) point index in the cloud */
    int64_t *value;          /* (CAP) code << 32 | key for the limits of slice 0 */
    int32_t *sel;            /* (CAP + 8) scratch: candidates inside a band */
    int32_t *bins;           /* (G, CAP) bin per grid; -1 outside a sector */
    int32_t *col;            /* (BLOCK + 8) scan output: columns in the block */
} lcs_buf;

/* ------------------------------------------------------------------------ per-point rules */

/* an element of type f32 / f64 at p (any alignment) as float64 */
LCS_INLINE double lcs_load(const char *p, int32_t type)
{
    if (type == LCS_F32) {
        float f;
        memcpy(&f, p, sizeof f);
        return (double)f;
    } else {
        double d;
        memcpy(&d, p, sizeof d);
        return d;
    }
}

/* atan(u) ~= u * sum(c_j * u**(2j)) on [0, 1]: converters/_kernels/cloud_slices.py ATAN_COEFFS */
#define LCS_C0 0.9999993356986212
#define LCS_C1 -0.33329861034289326
#define LCS_C2 0.19946567288244435
#define LCS_C3 -0.13908634232863948
#define LCS_C4 0.09642203544865086
#define LCS_C5 -0.05591235776154396
#define LCS_C6 0.021862952643013092
#define LCS_C7 -0.00405456031490202

/* atan2(y, x) within LCS_EPS for finite (x, y) not both 0 (NaN at the origin); octant fix-ups
 * as selects of constants, so the loops calling it vectorise */
LCS_INLINE double lcs_atan2_approx(double y, double x)
{
    const double ax = fabs(x), ay = fabs(y);
    const double lo = ay < ax ? ay : ax, hi = ay > ax ? ay : ax;
    const double z = lo / hi, u2 = z * z;
    double p = LCS_C7, a;
    p = p * u2 + LCS_C6;
    p = p * u2 + LCS_C5;
    p = p * u2 + LCS_C4;
    p = p * u2 + LCS_C3;
    p = p * u2 + LCS_C2;
    p = p * u2 + LCS_C1;
    p = p * u2 + LCS_C0;
    a = z * p;
    a = a + (ay > ax ? 1.0 : 0.0) * (0.5 * LCS_PI - 2.0 * a);
    a = a + (x < 0.0 ? 1.0 : 0.0) * (LCS_PI - 2.0 * a);
    return copysign(a, y);
}

/* the reference's bin of a point (converters._grid.AngleGrid.bins of atan2): -1 outside */
static int32_t lcs_bin_exact(double y, double x, double amin, double inc, int64_t size,
                             int64_t full)
{
    double d = atan2(y, x) - amin;
    int64_t k;
    if (!full) d = d - LCS_TWO_PI * floor((d + 0.5 * inc) / LCS_TWO_PI);
    k = (int64_t)ceil(d / inc - 0.5);
    if (full) {
        k %= size;
        return (int32_t)(k < 0 ? k + size : k);
    }
    return k >= 0 && k < size ? (int32_t)k : -1;
}

/* ------------------------------------------------------------------------------- stages */

/* 1. columns u0 .. u1 - 1 of a row whose height lies in [lo, hi], as u - u0 (returns how many) */
LCS_INLINE int64_t lcs_scan(const double *m, double lo, double hi, const char *xr,
                            const char *yr, const char *zr, int64_t step, int32_t type,
                            int64_t u0, int64_t u1, int32_t *col)
{
    int64_t u, c = 0;
    if (m[6] == 0.0 && m[7] == 0.0) {
        const double m8 = m[8], m11 = m[11];
        for (u = u0; u < u1; ++u) {
            const double pz = m8 * lcs_load(zr + u * step, type) + m11;
            col[c] = (int32_t)(u - u0);
            c += (pz >= lo) & (pz <= hi);
        }
        return c;
    }
    for (u = u0; u < u1; ++u) {
        const double x = lcs_load(xr + u * step, type), y = lcs_load(yr + u * step, type);
        const double pz = ((m[6] * x + m[7] * y) + m[8] * lcs_load(zr + u * step, type)) + m[11];
        col[c] = (int32_t)(u - u0);
        c += (pz >= lo) & (pz <= hi);
    }
    return c;
}

/* 2. the scanned points (columns col[0 .. n-1] after u0 in a row, cloud index key0 + column)
 * transformed into the buffers at positions c .. c + n - 1; a point with a non-finite
 * coordinate gets height NaN (inside no band) and x = y = 1 (a harmless bin); returns c + n */
LCS_INLINE int64_t lcs_take(const double *m, const char *xr, const char *yr, const char *zr,
                            int64_t step, int32_t type, int64_t u0, const int32_t *col,
                            int64_t n, int64_t key0, lcs_buf *b, int64_t c)
{
    double *restrict bx = b->x + c, *restrict by = b->y + c, *restrict bz = b->z + c;
    int64_t *restrict bk = b->key + c;
    int64_t q;
    for (q = 0; q < n; ++q) {
        const int64_t u = u0 + col[q];
        const double x = lcs_load(xr + u * step, type), y = lcs_load(yr + u * step, type);
        const double z = lcs_load(zr + u * step, type);
        const int ok = (fabs(x) <= DBL_MAX) & (fabs(y) <= DBL_MAX) & (fabs(z) <= DBL_MAX);
        const double px = ((m[0] * x + m[1] * y) + m[2] * z) + m[9];
        const double py = ((m[3] * x + m[4] * y) + m[5] * z) + m[10];
        const double pz = ((m[6] * x + m[7] * y) + m[8] * z) + m[11];
        bx[q] = ok ? px : 1.0;
        by[q] = ok ? py : 1.0;
        bz[q] = ok ? pz : NAN;
        bk[q] = key0 + u;
    }
    return c + n;
}

/* the positions j < n of the heights inside [lo, hi], into sel; returns how many */
LCS_INLINE int64_t lcs_band(const double *restrict bz, int64_t n, double lo, double hi,
                            int32_t *restrict sel)
{
    int64_t j, c = 0;
    for (j = 0; j < n; ++j) {
        sel[c] = (int32_t)j;
        c += (bz[j] >= lo) & (bz[j] <= hi);
    }
    return c;
}

#if LCS_AVX2
/* lane indices of the set bits of an 8-bit mask, packed from byte 0 (the rest 0) */
static const uint64_t lcs_compact[256] = {
    0x0000000000000000ULL, 0x0000000000000000ULL, 0x0000000000000001ULL, 0x0000000000000100ULL,
    0x0000000000000002ULL, 0x0000000000000200ULL, 0x0000000000000201ULL, 0x0000000000020100ULL,
    0x0000000000000003ULL, 0x0000000000000300ULL, 0x0000000000000301ULL, 0x0000000000030100ULL,
    0x0000000000000302ULL, 0x0000000000030200ULL, 0x0000000000030201ULL, 0x0000000003020100ULL,
    0x0000000000000004ULL, 0x0000000000000400ULL, 0x0000000000000401ULL, 0x0000000000040100ULL,
    0x0000000000000402ULL, 0x0000000000040200ULL, 0x0000000000040201ULL, 0x0000000004020100ULL,
    0x0000000000000403ULL, 0x0000000000040300ULL, 0x0000000000040301ULL, 0x0000000004030100ULL,
    0x0000000000040302ULL, 0x0000000004030200ULL, 0x0000000004030201ULL, 0x0000000403020100ULL,
    0x0000000000000005ULL, 0x0000000000000500ULL, 0x0000000000000501ULL, 0x0000000000050100ULL,
    0x0000000000000502ULL, 0x0000000000050200ULL, 0x0000000000050201ULL, 0x0000000005020100ULL,
    0x0000000000000503ULL, 0x0000000000050300ULL, 0x0000000000050301ULL, 0x0000000005030100ULL,
    0x0000000000050302ULL, 0x0000000005030200ULL, 0x0000000005030201ULL, 0x0000000503020100ULL,
    0x0000000000000504ULL, 0x0000000000050400ULL, 0x0000000000050401ULL, 0x0000000005040100ULL,
    0x0000000000050402ULL, 0x0000000005040200ULL, 0x0000000005040201ULL, 0x0000000504020100ULL,
    0x0000000000050403ULL, 0x0000000005040300ULL, 0x0000000005040301ULL, 0x0000000504030100ULL,
    0x0000000005040302ULL, 0x0000000504030200ULL, 0x0000000504030201ULL, 0x0000050403020100ULL,
    0x0000000000000006ULL, 0x0000000000000600ULL, 0x0000000000000601ULL, 0x0000000000060100ULL,
    0x0000000000000602ULL, 0x0000000000060200ULL, 0x0000000000060201ULL, 0x0000000006020100ULL,
    0x0000000000000603ULL, 0x0000000000060300ULL, 0x0000000000060301ULL, 0x0000000006030100ULL,
    0x0000000000060302ULL, 0x0000000006030200ULL, 0x0000000006030201ULL, 0x0000000603020100ULL,
    0x0000000000000604ULL, 0x0000000000060400ULL, 0x0000000000060401ULL, 0x0000000006040100ULL,
    0x0000000000060402ULL, 0x0000000006040200ULL, 0x0000000006040201ULL, 0x0000000604020100ULL,
    0x0000000000060403ULL, 0x0000000006040300ULL, 0x0000000006040301ULL, 0x0000000604030100ULL,
    0x0000000006040302ULL, 0x0000000604030200ULL, 0x0000000604030201ULL, 0x0000060403020100ULL,
    0x0000000000000605ULL, 0x0000000000060500ULL, 0x0000000000060501ULL, 0x0000000006050100ULL,
    0x0000000000060502ULL, 0x0000000006050200ULL, 0x0000000006050201ULL, 0x0000000605020100ULL,
    0x0000000000060503ULL, 0x0000000006050300ULL, 0x0000000006050301ULL, 0x0000000605030100ULL,
    0x0000000006050302ULL, 0x0000000605030200ULL, 0x0000000605030201ULL, 0x0000060503020100ULL,
    0x0000000000060504ULL, 0x0000000006050400ULL, 0x0000000006050401ULL, 0x0000000605040100ULL,
    0x0000000006050402ULL, 0x0000000605040200ULL, 0x0000000605040201ULL, 0x0000060504020100ULL,
    0x0000000006050403ULL, 0x0000000605040300ULL, 0x0000000605040301ULL, 0x0000060504030100ULL,
    0x0000000605040302ULL, 0x0000060504030200ULL, 0x0000060504030201ULL, 0x0006050403020100ULL,
    0x0000000000000007ULL, 0x0000000000000700ULL, 0x0000000000000701ULL, 0x0000000000070100ULL,
    0x0000000000000702ULL, 0x0000000000070200ULL, 0x0000000000070201ULL, 0x0000000007020100ULL,
    0x0000000000000703ULL, 0x0000000000070300ULL, 0x0000000000070301ULL, 0x0000000007030100ULL,
    0x0000000000070302ULL, 0x0000000007030200ULL, 0x0000000007030201ULL, 0x0000000703020100ULL,
    0x0000000000000704ULL, 0x0000000000070400ULL, 0x0000000000070401ULL, 0x0000000007040100ULL,
    0x0000000000070402ULL, 0x0000000007040200ULL, 0x0000000007040201ULL, 0x0000000704020100ULL,
    0x0000000000070403ULL, 0x0000000007040300ULL, 0x0000000007040301ULL, 0x0000000704030100ULL,
    0x0000000007040302ULL, 0x0000000704030200ULL, 0x0000000704030201ULL, 0x0000070403020100ULL,
    0x0000000000000705ULL, 0x0000000000070500ULL, 0x0000000000070501ULL, 0x0000000007050100ULL,
    0x0000000000070502ULL, 0x0000000007050200ULL, 0x0000000007050201ULL, 0x0000000705020100ULL,
    0x0000000000070503ULL, 0x0000000007050300ULL, 0x0000000007050301ULL, 0x0000000705030100ULL,
    0x0000000007050302ULL, 0x0000000705030200ULL, 0x0000000705030201ULL, 0x0000070503020100ULL,
    0x0000000000070504ULL, 0x0000000007050400ULL, 0x0000000007050401ULL, 0x0000000705040100ULL,
    0x0000000007050402ULL, 0x0000000705040200ULL, 0x0000000705040201ULL, 0x0000070504020100ULL,
    0x0000000007050403ULL, 0x0000000705040300ULL, 0x0000000705040301ULL, 0x0000070504030100ULL,
    0x0000000705040302ULL, 0x0000070504030200ULL, 0x0000070504030201ULL, 0x0007050403020100ULL,
    0x0000000000000706ULL, 0x0000000000070600ULL, 0x0000000000070601ULL, 0x0000000007060100ULL,
    0x0000000000070602ULL, 0x0000000007060200ULL, 0x0000000007060201ULL, 0x0000000706020100ULL,
    0x0000000000070603ULL, 0x0000000007060300ULL, 0x0000000007060301ULL, 0x0000000706030100ULL,
    0x0000000007060302ULL, 0x0000000706030200ULL, 0x0000000706030201ULL, 0x0000070603020100ULL,
    0x0000000000070604ULL, 0x0000000007060400ULL, 0x0000000007060401ULL, 0x0000000706040100ULL,
    0x0000000007060402ULL, 0x0000000706040200ULL, 0x0000000706040201ULL, 0x0000070604020100ULL,
    0x0000000007060403ULL, 0x0000000706040300ULL, 0x0000000706040301ULL, 0x0000070604030100ULL,
    0x0000000706040302ULL, 0x0000070604030200ULL, 0x0000070604030201ULL, 0x0007060403020100ULL,
    0x0000000000070605ULL, 0x0000000007060500ULL, 0x0000000007060501ULL, 0x0000000706050100ULL,
    0x0000000007060502ULL, 0x0000000706050200ULL, 0x0000000706050201ULL, 0x0000070605020100ULL,
    0x0000000007060503ULL, 0x0000000706050300ULL, 0x0000000706050301ULL, 0x0000070605030100ULL,
    0x0000000706050302ULL, 0x0000070605030200ULL, 0x0000070605030201ULL, 0x0007060503020100ULL,
    0x0000000007060504ULL, 0x0000000706050400ULL, 0x0000000706050401ULL, 0x0000070605040100ULL,
    0x0000000706050402ULL, 0x0000070605040200ULL, 0x0000070605040201ULL, 0x0007060504020100ULL,
    0x0000000706050403ULL, 0x0000070605040300ULL, 0x0000070605040301ULL, 0x0007060504030100ULL,
    0x0000070605040302ULL, 0x0007060504030200ULL, 0x0007060504030201ULL, 0x0706050403020100ULL,
};

/* float32 [zl, zh] holding every z whose height m8 * z + m11 (float64, upright target) lies in
 * [lo, hi], widened by far more than the rounding of those two operations: a prefilter (the
 * exact band tests come later, on the transformed height) */
static void lcs_z_bounds(const double *m, double lo, double hi, float *zl, float *zh)
{
    const double shift = fabs(m[11] / m[8]);
    double a = (lo - m[11]) / m[8], b = (hi - m[11]) / m[8];
    float fa, fb;
    if (m[8] < 0.0) {
        const double t = a;
        a = b, b = t;
    }
    a -= 1e-6 * (1.0 + fabs(a) + shift);
    b += 1e-6 * (1.0 + fabs(b) + shift);
    fa = (float)a, fb = (float)b;
    if ((double)fa > a) fa = nextafterf(fa, -INFINITY);
    if ((double)fb < b) fb = nextafterf(fb, INFINITY);
    *zl = fa, *zh = fb;
}

/* lcs_scan of packed 16-byte points with a float32 z, upright target: a superset of the points
 * in the hull (lcs_z_bounds), eight points from four contiguous loads (lanes in the order
 * 0 2 4 6 1 3 5 7: the fusion does not depend on the order of the points) */
LCS_TARGET static int64_t lcs_scan16_avx2(const char *zr, int64_t u0, int64_t u1, float zl,
                                          float zh, int32_t *col)
{
    const __m256i order = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
    const __m256 vlo = _mm256_set1_ps(zl), vhi = _mm256_set1_ps(zh);
    int64_t u, c = 0;
    /* (u + 8 < u1: the last load reads up to 15 bytes of point u + 8, which exists) */
    for (u = u0; u + 8 < u1; u += 8) {
        const float *z = (const float *)(const void *)(zr + 16 * u);
        const __m256 a = _mm256_loadu_ps(z), b = _mm256_loadu_ps(z + 8);
        const __m256 c_ = _mm256_loadu_ps(z + 16), d = _mm256_loadu_ps(z + 24);
        const __m256 zv = _mm256_shuffle_ps(_mm256_shuffle_ps(a, b, 0), _mm256_shuffle_ps(c_, d, 0),
                                            _MM_SHUFFLE(2, 0, 2, 0));
        const int mask = _mm256_movemask_ps(_mm256_and_ps(_mm256_cmp_ps(zv, vlo, _CMP_GE_OQ),
                                                          _mm256_cmp_ps(zv, vhi, _CMP_LE_OQ)));
        const __m256i perm =
            _mm256_cvtepu8_epi32(_mm_cvtsi64_si128((long long)lcs_compact[mask]));
        _mm256_storeu_si256((__m256i *)(void *)(col + c),
                            _mm256_add_epi32(_mm256_permutevar8x32_epi32(order, perm),
                                             _mm256_set1_epi32((int32_t)(u - u0))));
        c += __builtin_popcount((unsigned)mask);
    }
    for (; u < u1; ++u) {
        float z;
        memcpy(&z, zr + 16 * u, sizeof z);
        col[c] = (int32_t)(u - u0);
        c += (z >= zl) & (z <= zh);
    }
    return c;
}

/* lcs_take of float32 fields, eight points per step (gathers; the same formulas lane by
 * lane) */
LCS_TARGET static int64_t lcs_take_avx2(const double *m, const char *xr, const char *yr,
                                        const char *zr, int64_t step, int64_t u0,
                                        const int32_t *col, int64_t n, int64_t key0,
                                        lcs_buf *b, int64_t c)
{
    const __m256i vstep = _mm256_set1_epi32((int32_t)step);
    const __m256i first = _mm256_set1_epi64x(key0 + u0);
    const __m256d m0 = _mm256_set1_pd(m[0]), m1 = _mm256_set1_pd(m[1]);
    const __m256d m2 = _mm256_set1_pd(m[2]), m3 = _mm256_set1_pd(m[3]);
    const __m256d m4 = _mm256_set1_pd(m[4]), m5 = _mm256_set1_pd(m[5]);
    const __m256d m6 = _mm256_set1_pd(m[6]), m7 = _mm256_set1_pd(m[7]);
    const __m256d m8 = _mm256_set1_pd(m[8]), m9 = _mm256_set1_pd(m[9]);
    const __m256d m10 = _mm256_set1_pd(m[10]), m11 = _mm256_set1_pd(m[11]);
    const __m256d one = _mm256_set1_pd(1.0), nan = _mm256_set1_pd(NAN);
    const __m256d big = _mm256_set1_pd(DBL_MAX);
    const __m256d abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(0x7FFFFFFFFFFFFFFFLL));
    const float *xb = (const float *)(const void *)(xr + u0 * step);
    const float *yb = (const float *)(const void *)(yr + u0 * step);
    const float *zb = (const float *)(const void *)(zr + u0 * step);
    int64_t q;
    if (step > (1 << 20)) return lcs_take(m, xr, yr, zr, step, LCS_F32, u0, col, n, key0, b, c);
#define LCS_FINITE(v) _mm256_cmp_pd(_mm256_and_pd(v, abs_mask), big, _CMP_LE_OQ)
#define LCS_ROW(a, b_, c_, t) \
    _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(a, x), _mm256_mul_pd(b_, y)), \
                                _mm256_mul_pd(c_, z)), t)
    for (q = 0; q + 8 <= n; q += 8) {
        const __m256i cols = _mm256_loadu_si256((const __m256i *)(const void *)(col + q));
        const __m256i offsets = _mm256_mullo_epi32(cols, vstep);
        const __m256 xv = _mm256_i32gather_ps(xb, offsets, 1);
        const __m256 yv = _mm256_i32gather_ps(yb, offsets, 1);
        const __m256 zv = _mm256_i32gather_ps(zb, offsets, 1);
        int h;
        for (h = 0; h < 2; ++h) {
            const int64_t at = c + q + 4 * h;
            const __m128 xs = h ? _mm256_extractf128_ps(xv, 1) : _mm256_castps256_ps128(xv);
            const __m128 ys = h ? _mm256_extractf128_ps(yv, 1) : _mm256_castps256_ps128(yv);
            const __m128 zs = h ? _mm256_extractf128_ps(zv, 1) : _mm256_castps256_ps128(zv);
            const __m128i cs = h ? _mm256_extracti128_si256(cols, 1)
                                 : _mm256_castsi256_si128(cols);
            const __m256d x = _mm256_cvtps_pd(xs), y = _mm256_cvtps_pd(ys);
            const __m256d z = _mm256_cvtps_pd(zs);
            const __m256d ok = _mm256_and_pd(_mm256_and_pd(LCS_FINITE(x), LCS_FINITE(y)),
                                             LCS_FINITE(z));
            _mm256_storeu_pd(b->x + at, _mm256_blendv_pd(one, LCS_ROW(m0, m1, m2, m9), ok));
            _mm256_storeu_pd(b->y + at, _mm256_blendv_pd(one, LCS_ROW(m3, m4, m5, m10), ok));
            _mm256_storeu_pd(b->z + at, _mm256_blendv_pd(nan, LCS_ROW(m6, m7, m8, m11), ok));
            _mm256_storeu_si256((__m256i *)(void *)(b->key + at),
                                _mm256_add_epi64(_mm256_cvtepi32_epi64(cs), first));
        }
    }
#undef LCS_FINITE
#undef LCS_ROW
    return lcs_take(m, xr, yr, zr, step, LCS_F32, u0, col + q, n - q, key0, b, c + q);
}

/* lcs_band, eight heights per step (compaction by permutation) */
LCS_TARGET static int64_t lcs_band_avx2(const double *bz, int64_t n, double lo, double hi,
                                        int32_t *sel)
{
    const __m256i lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m256d vlo = _mm256_set1_pd(lo), vhi = _mm256_set1_pd(hi);
    int64_t j, c = 0, k;
    for (j = 0; j + 8 <= n; j += 8) {
        const __m256d z0 = _mm256_loadu_pd(bz + j), z1 = _mm256_loadu_pd(bz + j + 4);
        const int mask =
            _mm256_movemask_pd(_mm256_and_pd(_mm256_cmp_pd(z0, vlo, _CMP_GE_OQ),
                                             _mm256_cmp_pd(z0, vhi, _CMP_LE_OQ))) |
            (_mm256_movemask_pd(_mm256_and_pd(_mm256_cmp_pd(z1, vlo, _CMP_GE_OQ),
                                              _mm256_cmp_pd(z1, vhi, _CMP_LE_OQ)))
             << 4);
        const __m256i perm =
            _mm256_cvtepu8_epi32(_mm_cvtsi64_si128((long long)lcs_compact[mask]));
        _mm256_storeu_si256((__m256i *)(void *)(sel + c),
                            _mm256_add_epi32(_mm256_permutevar8x32_epi32(lanes, perm),
                                             _mm256_set1_epi32((int32_t)j)));
        c += __builtin_popcount((unsigned)mask);
    }
    k = lcs_band(bz + j, n - j, lo, hi, sel + c);
    for (; k > 0; --k, ++c) sel[c] += (int32_t)j;
    return c;
}

/* rho[j] = sqrt(x*x + y*y) for j < n (a multiple of 4): sqrt sets errno in C, so the compiler
 * keeps that loop scalar */
LCS_TARGET static void lcs_rho_avx2(const double *bx, const double *by, int64_t n, double *rho)
{
    int64_t j;
    for (j = 0; j < n; j += 4) {
        const __m256d x = _mm256_loadu_pd(bx + j), y = _mm256_loadu_pd(by + j);
        _mm256_storeu_pd(rho + j, _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(x, x),
                                                               _mm256_mul_pd(y, y))));
    }
}
#endif

/* 3. bins of n buffered points in one grid: -2 where the approximation cannot decide, fixed
 * after the vector loop */
LCS_INLINE void lcs_bins(const double *restrict px, const double *restrict py, int64_t n,
                         double amin, double inc, double inv, int64_t size, int64_t full,
                         int32_t *restrict out)
{
    const double fsize = (double)size, margin = 2.0 * LCS_EPS;
    int64_t j;
    int32_t undecided = 0;
    if (full) {
        for (j = 0; j < n; ++j) {
            const double e = (lcs_atan2_approx(py[j], px[j]) - amin) * inv - 0.5;
            const double edge = ceil(e) - e; /* bin edges: integer e; NaN at the origin */
            const double near = 1.0 - edge < edge ? 1.0 - edge : edge;
            double kf = ceil(e);
            int32_t k;
            kf = kf >= fsize ? kf - fsize : kf;
            kf = kf < 0.0 ? kf + fsize : kf;
            k = (near * inc > margin) & (fabs(e) < 1e9) & (kf >= 0.0) & (kf < fsize)
                    ? (int32_t)kf : -2;
            out[j] = k;
            undecided |= k == -2;
        }
    } else {
        const double half = 0.5 * inc, inv_2pi = 1.0 / LCS_TWO_PI;
        for (j = 0; j < n; ++j) {
            const double d = lcs_atan2_approx(py[j], px[j]) - amin;
            const double w = (d + half) * inv_2pi;
            const double fw = floor(w);
            const double wrap = fw + 1.0 - w < w - fw ? fw + 1.0 - w : w - fw;
            const double e = (d - LCS_TWO_PI * fw) * inv - 0.5;
            const double kf = ceil(e);
            const double edge = kf - e;
            const double near = 1.0 - edge < edge ? 1.0 - edge : edge;
            const int32_t inside = (kf >= 0.0) & (kf < fsize) ? (int32_t)kf : -1;
            const int32_t k = (near * inc > margin) & (fabs(e) < 1e9) &
                                      (wrap * LCS_TWO_PI > margin) ? inside : -2;
            out[j] = k;
            undecided |= k == -2;
        }
    }
    if (undecided)
        for (j = 0; j < n; ++j)
            if (out[j] == -2) out[j] = lcs_bin_exact(py[j], px[j], amin, inc, size, full);
}

/* code << 32 | key of a planar range for the limits [rl, rh] */
LCS_INLINE int64_t lcs_value(double rho, double rl, double rh, int64_t key)
{
    const float f = (float)rho;
    int32_t bits;
    int64_t code;
    memcpy(&bits, &f, sizeof bits);
    code = rho > FLT_MAX ? LCS_CODE_POS_INF : (int64_t)bits;
    code = rho < rl ? LCS_CODE_NEG_INF : code;
    code = rho > rh ? LCS_CODE_POS_INF : code;
    return (int64_t)(((uint64_t)code << 32) | (uint64_t)key);
}

/* 3.-5.: fuse the n buffered points into best */
LCS_INLINE void lcs_flush(const lcs_plan *p, lcs_buf *b, int64_t n, int64_t *best,
                          const int avx2)
{
    const double *restrict bx = b->x, *restrict by = b->y, *restrict bz = b->z;
    double *restrict rho = b->rho;
    int64_t *restrict value = b->value;
    const int64_t *restrict key = b->key;
    int32_t *restrict sel = b->sel;
    const double rl0 = p->rlo[0], rh0 = p->rhi[0];
    int64_t g, s, j;
    for (g = 0; g < p->n_grids; ++g)
        lcs_bins(bx, by, n, p->gmin[g], p->ginc[g], p->ginv[g], p->gsize[g], p->gfull[g],
                 b->bins + g * LCS_CAP);
#if LCS_AVX2
    if (avx2) lcs_rho_avx2(bx, by, n - n % 4, rho);
#endif
    for (j = avx2 ? n - n % 4 : 0; j < n; ++j) rho[j] = sqrt(bx[j] * bx[j] + by[j] * by[j]);
    for (j = 0; j < n; ++j) value[j] = lcs_value(rho[j], rl0, rh0, key[j]);
    for (s = 0; s < p->n_slices; ++s) {
        const double lo = p->zlo[s], hi = p->zhi[s], rl = p->rlo[s], rh = p->rhi[s];
        const int32_t *restrict bins = b->bins + p->sgrid[s] * LCS_CAP;
        int64_t *const row = best + p->soff[s];
        const int same = rl == rl0 && rh == rh0;
        int64_t scratch = LCS_EMPTY, n_in, q;
#if LCS_AVX2
        if (avx2)
            n_in = lcs_band_avx2(bz, n, lo, hi, sel);
        else
#endif
            n_in = lcs_band(bz, n, lo, hi, sel);
        for (q = 0; q < n_in; ++q) {
            const int32_t k = sel[q], bn = bins[k];
            const int64_t v = same ? value[k] : lcs_value(rho[k], rl, rh, key[k]);
            int64_t *const t = bn >= 0 ? row + bn : &scratch;
            *t = v < *t ? v : *t;
        }
    }
}

/* intensity element at p as float32 (a C cast: numpy's astype) */
LCS_INLINE float lcs_intensity(const char *p, int32_t type)
{
    union {
        float f;
        double d;
        uint8_t u8;
        uint16_t u16;
        uint32_t u32;
        int8_t i8;
        int16_t i16;
        int32_t i32;
    } e;
    switch (type) {
    case LCS_F32: memcpy(&e.f, p, 4); return e.f;
    case LCS_F64: memcpy(&e.d, p, 8); return (float)e.d;
    case LCS_U8: memcpy(&e.u8, p, 1); return (float)e.u8;
    case LCS_U16: memcpy(&e.u16, p, 2); return (float)e.u16;
    case LCS_U32: memcpy(&e.u32, p, 4); return (float)e.u32;
    case LCS_I8: memcpy(&e.i8, p, 1); return (float)e.i8;
    case LCS_I16: memcpy(&e.i16, p, 2); return (float)e.i16;
    default: memcpy(&e.i32, p, 4); return (float)e.i32;
    }
}

/* A cloud's field: element of point (v, u) at base + v * row_step + u * step. */
typedef struct {
    const char *base;
    int64_t step, row_step;
    int32_t type;
} lcs_field;

/* 1.-5. over the whole cloud (h rows of w points; x, y, z share step, row step and type) */
LCS_INLINE void lcs_fuse_impl(const lcs_plan *p, int64_t h, int64_t w, const lcs_field *xf,
                              const lcs_field *yf, const lcs_field *zf, lcs_buf *b,
                              int64_t *best, const int avx2)
{
    const int64_t step = zf->step;
    const int32_t type = zf->type;
    const int packed16 = avx2 && type == LCS_F32 && step == 16 && p->m[6] == 0.0 &&
                         p->m[7] == 0.0;
    float zl = 0.0f, zh = 0.0f;
    int64_t v, u0, c = 0;
#if LCS_AVX2
    if (packed16) lcs_z_bounds(p->m, p->zall_lo, p->zall_hi, &zl, &zh);
#endif
    for (v = 0; v < h; ++v) {
        const char *xr = xf->base + v * xf->row_step, *yr = yf->base + v * yf->row_step;
        const char *zr = zf->base + v * zf->row_step;
        for (u0 = 0; u0 < w; u0 += LCS_BLOCK) {
            const int64_t u1 = w - u0 < LCS_BLOCK ? w : u0 + LCS_BLOCK;
            int64_t n;
#if LCS_AVX2
            if (packed16)
                n = lcs_scan16_avx2(zr, u0, u1, zl, zh, b->col);
            else
#endif
                n = lcs_scan(p->m, p->zall_lo, p->zall_hi, xr, yr, zr, step, type, u0, u1,
                             b->col);
#if LCS_AVX2
            if (avx2 && type == LCS_F32)
                c = lcs_take_avx2(p->m, xr, yr, zr, step, u0, b->col, n, v * w, b, c);
            else
#endif
                c = lcs_take(p->m, xr, yr, zr, step, type, u0, b->col, n, v * w, b, c);
            if (c > LCS_CAP - LCS_BLOCK) {
                lcs_flush(p, b, c, best, avx2);
                c = 0;
            }
        }
    }
    if (c) lcs_flush(p, b, c, best, avx2);
}

static void lcs_fuse_base(const lcs_plan *p, int64_t h, int64_t w, const lcs_field *xf,
                          const lcs_field *yf, const lcs_field *zf, lcs_buf *b, int64_t *best)
{
    lcs_fuse_impl(p, h, w, xf, yf, zf, b, best, 0);
}

#if LCS_AVX2
LCS_TARGET static void lcs_fuse_avx2(const lcs_plan *p, int64_t h, int64_t w,
                                     const lcs_field *xf, const lcs_field *yf,
                                     const lcs_field *zf, lcs_buf *b, int64_t *best)
{
    lcs_fuse_impl(p, h, w, xf, yf, zf, b, best, 1);
}

static int lcs_avx2_ok(void)
{
    static int known = -1;
    if (known < 0) known = __builtin_cpu_supports("avx2") ? 1 : 0;
    return known;
}
#endif

/* Whether lcs_slices takes the AVX2 path on this CPU (with simd = 1). */
LCS_EXPORT int32_t lcs_vectorised(void)
{
#if LCS_AVX2
    return lcs_avx2_ok();
#else
    return 0;
#endif
}

/*
 * All slices of one cloud of h rows of w points (point (v, u) is number v * w + u):
 *   x, y, z: addresses of point (0, 0)'s coordinates, all of type LCS_F32 or all LCS_F64,
 *   point (v, u)'s at + v * row_step + u * step (bytes, native byte order, any alignment);
 *   best: (plan size) int64 reduction array, written (code << 32 | point; EMPTY for no point);
 *   ranges: (plan size) float32 published ranges, or NULL (fusion only);
 *   inten: address of point (0, 0)'s intensity (type code inten_type, steps i_step and
 *   i_row_step) or NULL; ints: (plan size) float32 winners' intensities (0 for an empty bin),
 *   written when ranges, ints and inten are not NULL;
 *   simd: 0 forces the scalar build.
 * Returns 0, -1 when out of memory, -2 for a bad type code, -3 for a bad plan or size.
 */
LCS_EXPORT int64_t lcs_slices(const lcs_plan *p, int64_t h, int64_t w, const char *x,
                              const char *y, const char *z, int64_t step, int64_t row_step,
                              int32_t type, const char *inten, int64_t i_step,
                              int64_t i_row_step, int32_t inten_type, int64_t *best,
                              float *ranges, float *ints, int32_t simd)
{
    const int64_t g_n = p->n_grids;
    const lcs_field xf = {x, step, row_step, type}, yf = {y, step, row_step, type};
    const lcs_field zf = {z, step, row_step, type};
    lcs_buf b;
    char *mem;
    int64_t s, k;
    if (p->n_slices < 1 || g_n < 1 || h < 0 || w < 0) return -3;
    if (type != LCS_F32 && type != LCS_F64) return -2;
    if (inten && (inten_type < LCS_F32 || inten_type > LCS_I32)) return -2;
    for (k = 0; k < p->size; ++k) best[k] = LCS_EMPTY;
    if (h > 0 && w > 0) {
        mem = (char *)malloc((size_t)LCS_CAP * (4 * sizeof(double) + 2 * sizeof(int64_t) +
                                                (1 + (size_t)g_n) * sizeof(int32_t)) +
                             (LCS_BLOCK + 16) * sizeof(int32_t));
        if (!mem) return -1;
        b.x = (double *)(void *)mem, b.y = b.x + LCS_CAP, b.z = b.y + LCS_CAP;
        b.rho = b.z + LCS_CAP;
        b.key = (int64_t *)(void *)(b.rho + LCS_CAP), b.value = b.key + LCS_CAP;
        b.bins = (int32_t *)(void *)(b.value + LCS_CAP), b.col = b.bins + g_n * LCS_CAP;
        b.sel = b.col + LCS_BLOCK + 8; /* (each with 8 entries of slack for vector stores) */
#if LCS_AVX2
        if (simd && lcs_avx2_ok())
            lcs_fuse_avx2(p, h, w, &xf, &yf, &zf, &b, best);
        else
#endif
            lcs_fuse_base(p, h, w, &xf, &yf, &zf, &b, best);
        free(mem);
    }
    (void)simd;
    if (!ranges) return 0;
    for (s = 0; s < p->n_slices; ++s) {
        const int64_t off = p->soff[s], n = p->gsize[p->sgrid[s]];
        const float inf_v = p->inf_value[s], fill_v = p->fill_value[s];
        for (k = off; k < off + n; ++k) {
            const int64_t v = best[k], code = v >> 32;
            if (v == LCS_EMPTY) {
                ranges[k] = fill_v;
                if (ints) ints[k] = 0.0f;
                continue;
            }
            if (code < LCS_CODE_NEG_INF) {
                const int32_t bits = (int32_t)code;
                memcpy(ranges + k, &bits, sizeof bits);
            } else {
                ranges[k] = code == LCS_CODE_NEG_INF   ? -INFINITY
                            : code == LCS_CODE_POS_INF ? inf_v
                                                       : NAN;
            }
            if (ints && inten) {
                const int64_t key = v & 0xFFFFFFFF;
                const int64_t row = i_row_step == w * i_step ? 0 : key / w;
                ints[k] = lcs_intensity(inten + row * i_row_step + (key - row * w) * i_step,
                                        inten_type);
            }
        }
    }
    return 0;
}

/* ------------------------------------------------------------- (empty) Python module */

static struct PyModuleDef lcs_module = {
    PyModuleDef_HEAD_INIT, "_cloudslicekernel",
    "Compiled PointCloud2 -> LaserScan slices kernel (loaded with ctypes by "
    "converters._kernels.cloud_slices).",
    -1, NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__cloudslicekernel(void)
{
    PyObject *module = PyModule_Create(&lcs_module);
    if (module && PyModule_AddIntConstant(module, "ABI", LCS_ABI) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
