/*
 * Optional compiled kernel of converters.laserscan: height slices of a LidarScan in the
 * row-ordered configuration (converters/_grid.py, "row-ordered kernel"), fusion and decoding in
 * one call. Results are bit-identical to the numba kernel converters._kernels.slices_numba._row_convert (the
 * rules are in the docstring of converters/_grid.py; this file only evaluates them).
 *
 * What makes it fast: in that configuration every row u of the scan maps its columns onto the
 * bins of the (full-circle, sensor-resolution) grid as bin = (start[u] + step[u] * c) mod W,
 * step = +-1, and the height band of a point is a float32 range interval per row
 * (band_intervals_f32). So the scan is read row by row, in pixel order, with no gather: the
 * range and the four ray tables (dx, dy, ox, oy) are contiguous streams, and the eight points of
 * a group update eight *consecutive* bins of every slice (a masked vector minimum; reversed for
 * step = -1). To keep the bins consecutive across the seam, each slice has an unfolded
 * reduction row of 2W entries (position start + c, or start + W - c), folded (bin b = min of
 * positions b and b + W) when decoding.
 *
 * Arithmetic, exactly as the numba kernel (build with -ffp-contract=off, never -ffast-math):
 *   x = (double)r * dx + ox, y = (double)r * dy + oy, rho = sqrt(x * x + y * y)   (float64,
 *   each product and sum rounded); code = the float32 bits of (float)rho, sign-extended, or
 *   CODE_NEG_INF (rho < lim_lo) / CODE_POS_INF (rho > lim_hi); value = code << 32 | key.
 * Points closer than their far-field threshold r_thr take their bin from atan2 (libm, float64).
 *
 * Two implementations of the per-pixel rules, the same results: a scalar one (any CPU, and the
 * group tails) and an AVX-512 one (eight pixels per step), picked at run time; `simd = 0` forces
 * the scalar one (tests run both). The Python module part is empty: converters/laserscan.py
 * loads this shared object with ctypes; lss_slices() releases the GIL.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Bump with any change of lss_plan or of a function's signature or semantics. */
#define LSS_ABI 2

#define LSS_EMPTY INT64_MAX
#define LSS_CODE_NEG_INF 0x7F800000
#define LSS_CODE_POS_INF 0x7F800001
#define LSS_CODE_NAN 0x7F800002
#define LSS_MAX_SLICES 32
#define LSS_PAD 8 /* int64 entries before and after each unfolded reduction row */

#if defined(_WIN32)
#define LSS_EXPORT __declspec(dllexport)
#else
#define LSS_EXPORT __attribute__((visibility("default")))
#endif

#if defined(__GNUC__) || defined(__clang__)
#define LSS_INLINE static inline __attribute__((always_inline))
#else
#define LSS_INLINE static inline
#endif

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define LSS_AVX512 1
#include <immintrin.h>
#else
#define LSS_AVX512 0
#endif

/* Intensity element types (the codes laserscan.py passes). */
enum { LSS_F32, LSS_F64, LSS_U8, LSS_U16, LSS_U32, LSS_I8, LSS_I16, LSS_I32 };

/*
 * Everything but the scan: built once per table version by laserscan.py (a ctypes Structure
 * with the same fields in the same order). Arrays are C-contiguous; H rows, W columns, S slices.
 */
typedef struct {
    int64_t height, width, n_slices;
    const float *dx, *dy, *ox, *oy;  /* (H*W) ray tables in the target frame, pixel order */
    const float *r_thr;              /* (H*W) far-field threshold (rounded up), pixel order */
    const float *group_thr;          /* (H, ceil(W/8)) largest r_thr of each group of 8 */
    const int64_t *bin_start;        /* (H) 0 <= start < W: bin of (u, c) = start + step*c mod W */
    const int64_t *bin_step;         /* (H) +1 or -1 */
    const int64_t *key_start;        /* (H) tie key of (u, c) = u*W + (kstart + kstep*c mod W) */
    const int64_t *key_step;         /* (H) +1 or -1 */
    const uint32_t *qf, *qn;         /* bit s: slice s may report +Inf/NaN (qf), -Inf (qn) */
    int64_t q_per_pixel;             /* 0: qf, qn are (H) per row; 1: (H*W) pixel order */
    const float *lo, *hi;            /* (S, H) band interval of each slice and row */
    double lim_lo, lim_hi;           /* planar range limits (inclusive) */
    double g_min, g_inc;             /* grid: angle_min, increment (W bins) */
    int64_t g_full;                  /* the grid is a full circle */
    const float *inf_value, *fill_value; /* (S) decoded +Inf and empty-bin values */
    const int64_t *key_to_pos;       /* (H*W) tie key -> pixel, or NULL (key = pixel) */
} lss_plan;

LSS_EXPORT int32_t lss_abi(void) { return LSS_ABI; }
LSS_EXPORT int64_t lss_plan_size(void) { return (int64_t)sizeof(lss_plan); }

/* ------------------------------------------------------------------------ per-pixel rules */

/* code << 32 | key, two's complement (code may be negative: a NaN rho's sign-extended bits) */
LSS_INLINE int64_t lss_pack(int64_t code, int64_t key)
{
    return (int64_t)(((uint64_t)code << 32) | (uint64_t)key);
}

/* the class code of a point's planar range rho */
LSS_INLINE int64_t lss_code(double rho, double lim_lo, double lim_hi)
{
    const float f = (float)rho;
    int32_t bits;
    int64_t code;
    memcpy(&bits, &f, sizeof bits);
    code = bits;
    if (rho < lim_lo) code = LSS_CODE_NEG_INF;
    if (rho > lim_hi) code = LSS_CODE_POS_INF;
    return code;
}

/* tie key of pixel (u, c) */
LSS_INLINE int64_t lss_key(const lss_plan *p, int64_t u, int64_t c)
{
    int64_t k = (p->key_start[u] + p->key_step[u] * c) % p->width;
    if (k < 0) k += p->width;
    return u * p->width + k;
}

/* Unfolded reduction row of slice s: position start + c (step +1) or start + W - c (step -1),
 * positions b and b + W being bin b. */
LSS_INLINE int64_t *lss_ext(int64_t *ext, const lss_plan *p, int64_t s)
{
    return ext + s * (2 * p->width + 2 * LSS_PAD) + LSS_PAD;
}

/* A point closer than its far-field threshold: its bin from atan2, its value into the slices
 * of mask m (converters._kernels.slices_numba._near_point). */
static void lss_near(const lss_plan *p, int64_t *ext, int64_t pix, int64_t key, float rv,
                     uint32_t m)
{
    const double rd = (double)rv;
    const double x = rd * (double)p->dx[pix] + (double)p->ox[pix];
    const double y = rd * (double)p->dy[pix] + (double)p->oy[pix];
    const double rho = sqrt(x * x + y * y);
    const int64_t value = lss_pack(lss_code(rho, p->lim_lo, p->lim_hi), key);
    const int64_t size = p->width;
    double d = atan2(y, x) - p->g_min;
    int64_t bn, s;
    if (p->g_full) {
        bn = (int64_t)ceil(d / p->g_inc - 0.5);
        if (bn < 0 || bn >= size) {
            bn %= size;
            if (bn < 0) bn += size;
        }
    } else {
        const double two_pi = 2.0 * 3.141592653589793;
        d = d - two_pi * floor((d + 0.5 * p->g_inc) / two_pi);
        bn = (int64_t)ceil(d / p->g_inc - 0.5);
        if (bn < 0 || bn >= size) return;
    }
    for (s = 0; s < p->n_slices; ++s) {
        if ((m >> s) & 1u) {
            int64_t *e = lss_ext(ext, p, s) + bn;
            if (value < *e) *e = value;
        }
    }
}

/* Slice mask of a range at pixel `pix` of row u: for a point, the bands it is inside; for a
 * non-point, the slices its class qualifies for. */
LSS_INLINE uint32_t lss_mask(const lss_plan *p, int64_t u, int64_t pix, float rv)
{
    const int64_t h = p->height;
    const int64_t q = p->q_per_pixel ? pix : u;
    uint32_t m = 0;
    int64_t s;
    if (rv > 0.0f && rv < INFINITY) {
        for (s = 0; s < p->n_slices; ++s)
            m |= (uint32_t)((rv >= p->lo[s * h + u]) & (rv <= p->hi[s * h + u])) << s;
        return m;
    }
    return rv == -INFINITY ? p->qn[q] : p->qf[q];
}

/* Pixels c0 .. c1 - 1 of row u, one at a time (any CPU; the tails of the vector path). */
static void lss_pixels(const lss_plan *p, const float *r, int64_t *ext, int64_t u, int64_t c0,
                       int64_t c1)
{
    const int64_t w = p->width;
    const int64_t start = p->bin_start[u], step = p->bin_step[u];
    int64_t c, s;
    for (c = c0; c < c1; ++c) {
        const int64_t pix = u * w + c;
        const float rv = r[pix];
        const int point = rv > 0.0f && rv < INFINITY;
        const uint32_t m = lss_mask(p, u, pix, rv);
        const int64_t key = lss_key(p, u, c);
        const int64_t pos = step > 0 ? start + c : start + w - c;
        int64_t value;
        if (!m) continue;
        if (point && rv < p->r_thr[pix]) {
            lss_near(p, ext, pix, key, rv, m);
            continue;
        }
        if (point) {
            const double rd = (double)rv;
            const double x = rd * (double)p->dx[pix] + (double)p->ox[pix];
            const double y = rd * (double)p->dy[pix] + (double)p->oy[pix];
            value = lss_pack(lss_code(sqrt(x * x + y * y), p->lim_lo, p->lim_hi), key);
        } else {
            value = lss_pack(rv == INFINITY    ? LSS_CODE_POS_INF
                             : rv == -INFINITY ? LSS_CODE_NEG_INF
                                               : LSS_CODE_NAN,
                             key);
        }
        for (s = 0; s < p->n_slices; ++s) {
            if ((m >> s) & 1u) {
                int64_t *e = lss_ext(ext, p, s) + pos;
                if (value < *e) *e = value;
            }
        }
    }
}

#if LSS_AVX512
#define LSS_TARGET __attribute__((target("avx512f,avx512vl,avx512dq,avx512bw")))

/* Per-row constants of the vector path: each row's *live* slices (a nonempty band interval or
 * a qualifier; a row pointing up never sees a band below the sensor, for instance), compacted. */
typedef struct {
    int64_t stride;         /* = n_slices */
    int32_t *count;         /* (H) live slices of each row */
    int32_t *slice;         /* (H, stride) their indices */
    float *lo, *hi;         /* (H, stride) their band intervals */
    uint8_t *qf, *qn;       /* (H, stride) 0xFF where the slice qualifies the class (per-row q) */
} lss_rows;

/* 8 lanes of slice t (of the block): in the band, or a qualified non-point */
#define LSS_SLICE_MASK(t)                                                                   \
    (_mm256_mask_cmp_ps_mask(_mm256_cmp_ps_mask(rv, lo##t, _CMP_GE_OQ), rv, hi##t,         \
                             _CMP_LE_OQ) |                                                 \
     (per_pixel ? (__mmask8)(_mm256_mask_test_epi32_mask(far_q, qf8, bit##t) |             \
                             _mm256_mask_test_epi32_mask(neg, qn8, bit##t))                \
                : (__mmask8)((far_q & qf##t) | (neg & qn##t))))

/* min-update of the 8 consecutive positions of slice t's reduction row */
#define LSS_UPDATE(t)                                                                       \
    _mm512_storeu_si512(e##t + at, _mm512_min_epi64(_mm512_loadu_si512(e##t + at),          \
                                                    _mm512_mask_mov_epi64(empty, m##t, value)))

/* Row u, its live slices j0 .. j0 + ns - 1 (ns <= 4: the block), groups of eight pixels
 * (columns 0 .. W - W % 8 - 1); the same rules as lss_pixels. Lane i of a group is column c + i
 * (rev = 0, the row's bins ascend) or c + 7 - i (rev = 1, they descend), so lane i always goes
 * to position at + i. ns and rev are constants in each expansion (lss_row_avx512). */
LSS_TARGET LSS_INLINE void lss_row_avx512_impl(const lss_plan *p, const lss_rows *t,
                                               const float *r, int64_t *ext, int64_t u,
                                               int64_t j0, const int ns, const int rev)
{
    const int64_t w = p->width, row = u * t->stride + j0;
    const int32_t *sl = t->slice + row;
    const int64_t kstep = p->key_step[u];
    const int per_pixel = p->q_per_pixel != 0;
    const float *restrict gthr = p->group_thr + u * ((w + 7) / 8);
    const float *restrict dx = p->dx, *restrict dy = p->dy, *restrict ox = p->ox;
    const float *restrict oy = p->oy, *restrict r_thr = p->r_thr;
    const uint32_t *restrict qf = p->qf, *restrict qn = p->qn;
    const __m256 zero = _mm256_setzero_ps(), inf = _mm256_set1_ps(INFINITY);
    const __m256 minf = _mm256_set1_ps(-INFINITY);
    /* (a slice k >= ns of the block: empty band, no qualifier, never read) */
    const __m256 lo0 = _mm256_set1_ps(t->lo[row]);
    const __m256 lo1 = ns > 1 ? _mm256_set1_ps(t->lo[row + 1]) : inf;
    const __m256 lo2 = ns > 2 ? _mm256_set1_ps(t->lo[row + 2]) : inf;
    const __m256 lo3 = ns > 3 ? _mm256_set1_ps(t->lo[row + 3]) : inf;
    const __m256 hi0 = _mm256_set1_ps(t->hi[row]);
    const __m256 hi1 = ns > 1 ? _mm256_set1_ps(t->hi[row + 1]) : zero;
    const __m256 hi2 = ns > 2 ? _mm256_set1_ps(t->hi[row + 2]) : zero;
    const __m256 hi3 = ns > 3 ? _mm256_set1_ps(t->hi[row + 3]) : zero;
    const __mmask8 qf0 = t->qf[row], qf1 = ns > 1 ? t->qf[row + 1] : 0;
    const __mmask8 qf2 = ns > 2 ? t->qf[row + 2] : 0, qf3 = ns > 3 ? t->qf[row + 3] : 0;
    const __mmask8 qn0 = t->qn[row], qn1 = ns > 1 ? t->qn[row + 1] : 0;
    const __mmask8 qn2 = ns > 2 ? t->qn[row + 2] : 0, qn3 = ns > 3 ? t->qn[row + 3] : 0;
    const __m256i bit0 = _mm256_set1_epi32((int32_t)(1u << sl[0]));
    const __m256i bit1 = _mm256_set1_epi32(ns > 1 ? (int32_t)(1u << sl[1]) : 0);
    const __m256i bit2 = _mm256_set1_epi32(ns > 2 ? (int32_t)(1u << sl[2]) : 0);
    const __m256i bit3 = _mm256_set1_epi32(ns > 3 ? (int32_t)(1u << sl[3]) : 0);
    const __m512d lim_lo = _mm512_set1_pd(p->lim_lo), lim_hi = _mm512_set1_pd(p->lim_hi);
    const __m256i flip = _mm256_set_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    const __m512i lanes = rev ? _mm512_set_epi64(0, 1, 2, 3, 4, 5, 6, 7)
                              : _mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0);
    const __m512i key_lanes = _mm512_mullo_epi64(lanes, _mm512_set1_epi64(kstep));
    const __m512i wv = _mm512_set1_epi64(w), row_key = _mm512_set1_epi64(u * w);
    const __m512i empty = _mm512_set1_epi64(LSS_EMPTY);
    const __m512i neg_inf_code = _mm512_set1_epi64(LSS_CODE_NEG_INF);
    const __m512i pos_inf_code = _mm512_set1_epi64(LSS_CODE_POS_INF);
    const __m512i nan_code = _mm512_set1_epi64(LSS_CODE_NAN);
    /* position of lane 0 of column c's group: start + c, or start + W - c - 7 */
    const int64_t base = rev ? p->bin_start[u] + w - 7 : p->bin_start[u];
    int64_t *const e0 = lss_ext(ext, p, sl[0]) + base;
    int64_t *const e1 = ns > 1 ? lss_ext(ext, p, sl[1]) + base : e0;
    int64_t *const e2 = ns > 2 ? lss_ext(ext, p, sl[2]) + base : e0;
    int64_t *const e3 = ns > 3 ? lss_ext(ext, p, sl[3]) + base : e0;
    int64_t key_col = lss_key(p, u, 0) - u * w - 8 * kstep; /* key column of column c */
    int64_t g;
#define LSS_LOAD(a) (rev ? _mm256_permutexvar_ps(flip, _mm256_loadu_ps(a)) : _mm256_loadu_ps(a))
    for (g = 0; g < w / 8; ++g) {
        const int64_t c = 8 * g, pix = u * w + c, at = rev ? -c : c;
        const __m256 rv = LSS_LOAD(r + pix);
        const __mmask8 point = _mm256_mask_cmp_ps_mask(_mm256_cmp_ps_mask(rv, zero, _CMP_GT_OQ),
                                                       rv, inf, _CMP_LT_OQ);
        const __mmask8 other = (__mmask8)~point;
        const __mmask8 neg = _mm256_mask_cmp_ps_mask(other, rv, minf, _CMP_EQ_OQ);
        const __mmask8 far_q = other & (__mmask8)~neg; /* +Inf, NaN, 0, negative */
        __m256i qf8 = _mm256_setzero_si256(), qn8 = _mm256_setzero_si256();
        __mmask8 m0, m1, m2, m3, near = 0;
        key_col += 8 * kstep;
        if (key_col >= w) key_col -= w;
        if (key_col < 0) key_col += w;
        if (per_pixel) {
            qf8 = _mm256_castps_si256(LSS_LOAD((const float *)(qf + pix)));
            qn8 = _mm256_castps_si256(LSS_LOAD((const float *)(qn + pix)));
        }
        m0 = LSS_SLICE_MASK(0);
        m1 = ns > 1 ? LSS_SLICE_MASK(1) : 0;
        m2 = ns > 2 ? LSS_SLICE_MASK(2) : 0;
        m3 = ns > 3 ? LSS_SLICE_MASK(3) : 0;
        if (!(m0 | m1 | m2 | m3)) continue;
        /* points closer than their far-field threshold: the atan2 path, out of the minima */
        if (_mm256_mask_cmp_ps_mask(point, rv, _mm256_set1_ps(gthr[g]), _CMP_LT_OQ))
            near = _mm256_mask_cmp_ps_mask(point, rv, LSS_LOAD(r_thr + pix), _CMP_LT_OQ);
        if (near) {
            int i;
            for (i = 0; i < 8; ++i) {
                const int col = rev ? 7 - i : i;
                const uint32_t bits = (((m0 >> i) & 1u) << sl[0]) |
                                      (ns > 1 ? ((m1 >> i) & 1u) << sl[1] : 0) |
                                      (ns > 2 ? ((m2 >> i) & 1u) << sl[2] : 0) |
                                      (ns > 3 ? ((m3 >> i) & 1u) << sl[3] : 0);
                if (((near >> i) & 1) && bits)
                    lss_near(p, ext, pix + col, u * w + (key_col + kstep * col + w) % w,
                             r[pix + col], bits);
            }
            m0 &= (__mmask8)~near, m1 &= (__mmask8)~near;
            m2 &= (__mmask8)~near, m3 &= (__mmask8)~near;
        }
        {
            const __m512d rd = _mm512_cvtps_pd(rv);
            const __m512d x = _mm512_add_pd(_mm512_mul_pd(rd, _mm512_cvtps_pd(LSS_LOAD(dx + pix))),
                                            _mm512_cvtps_pd(LSS_LOAD(ox + pix)));
            const __m512d y = _mm512_add_pd(_mm512_mul_pd(rd, _mm512_cvtps_pd(LSS_LOAD(dy + pix))),
                                            _mm512_cvtps_pd(LSS_LOAD(oy + pix)));
            const __m512d rho = _mm512_sqrt_pd(_mm512_add_pd(_mm512_mul_pd(x, x),
                                                             _mm512_mul_pd(y, y)));
            const __mmask8 pos_inf = _mm256_mask_cmp_ps_mask(other, rv, inf, _CMP_EQ_OQ);
            __m512i code = _mm512_cvtepi32_epi64(_mm256_castps_si256(_mm512_cvtpd_ps(rho)));
            __m512i key = _mm512_add_epi64(_mm512_set1_epi64(key_col), key_lanes);
            __m512i value;
            code = _mm512_mask_mov_epi64(code, _mm512_cmp_pd_mask(rho, lim_lo, _CMP_LT_OQ),
                                         neg_inf_code);
            code = _mm512_mask_mov_epi64(code, _mm512_cmp_pd_mask(rho, lim_hi, _CMP_GT_OQ),
                                         pos_inf_code);
            code = _mm512_mask_mov_epi64(code, other, nan_code);
            code = _mm512_mask_mov_epi64(code, pos_inf, pos_inf_code);
            code = _mm512_mask_mov_epi64(code, neg, neg_inf_code);
            /* key column wraps at most once inside a group of eight */
            key = _mm512_mask_add_epi64(key, _mm512_cmplt_epi64_mask(key, _mm512_setzero_si512()),
                                        key, wv);
            key = _mm512_mask_sub_epi64(key, _mm512_cmpge_epi64_mask(key, wv), key, wv);
            value = _mm512_or_si512(_mm512_slli_epi64(code, 32), _mm512_add_epi64(key, row_key));
            LSS_UPDATE(0);
            if (ns > 1) LSS_UPDATE(1);
            if (ns > 2) LSS_UPDATE(2);
            if (ns > 3) LSS_UPDATE(3);
        }
    }
#undef LSS_LOAD
}

/* Row u, all its live slices, by blocks of up to four. */
LSS_TARGET static void lss_row_avx512(const lss_plan *p, const lss_rows *t, const float *r,
                                      int64_t *ext, int64_t u)
{
    const int rev = p->bin_step[u] < 0;
    const int64_t count = t->count[u];
    int64_t j0;
    for (j0 = 0; j0 < count; j0 += 4) {
        switch (2 * (count - j0 < 4 ? count - j0 : 4) + rev) {
        case 2: lss_row_avx512_impl(p, t, r, ext, u, j0, 1, 0); break;
        case 3: lss_row_avx512_impl(p, t, r, ext, u, j0, 1, 1); break;
        case 4: lss_row_avx512_impl(p, t, r, ext, u, j0, 2, 0); break;
        case 5: lss_row_avx512_impl(p, t, r, ext, u, j0, 2, 1); break;
        case 6: lss_row_avx512_impl(p, t, r, ext, u, j0, 3, 0); break;
        case 7: lss_row_avx512_impl(p, t, r, ext, u, j0, 3, 1); break;
        case 8: lss_row_avx512_impl(p, t, r, ext, u, j0, 4, 0); break;
        default: lss_row_avx512_impl(p, t, r, ext, u, j0, 4, 1); break;
        }
    }
}

static int lss_avx512_ok(void)
{
    static int known = -1;
    if (known < 0)
        known = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl") &&
                __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512bw");
    return known;
}
#endif

/* Whether lss_slices takes the vector path on this CPU (with simd = 1). */
LSS_EXPORT int32_t lss_vectorised(void)
{
#if LSS_AVX512
    return lss_avx512_ok();
#else
    return 0;
#endif
}

/* intensity[pix] as float32 (a C cast: numpy's astype); 0 for an unknown type */
LSS_INLINE float lss_intensity(const void *src, int32_t type, int64_t pix)
{
    switch (type) {
    case LSS_F32: return ((const float *)src)[pix];
    case LSS_F64: return (float)((const double *)src)[pix];
    case LSS_U8: return (float)((const uint8_t *)src)[pix];
    case LSS_U16: return (float)((const uint16_t *)src)[pix];
    case LSS_U32: return (float)((const uint32_t *)src)[pix];
    case LSS_I8: return (float)((const int8_t *)src)[pix];
    case LSS_I16: return (float)((const int16_t *)src)[pix];
    case LSS_I32: return (float)((const int32_t *)src)[pix];
    default: return 0.0f;
    }
}

/*
 * All slices of one scan: ranges r (H*W float32 metres, pixel order) -> ranges_out (S*W
 * float32, slices back to back), plus, when `intensity` is not NULL, the winners' intensities
 * (element type `intensity_type`, H*W) cast to float32 into ints_out (0 for an empty bin), plus,
 * when `winners` is not NULL, the winners' tie keys (-1 for an empty bin).
 * Returns 0, -1 when out of memory, -2 for an unknown intensity type, -3 for a bad plan.
 */
LSS_EXPORT int64_t lss_slices(const lss_plan *p, const float *r, const void *intensity,
                              int32_t intensity_type, float *ranges_out, float *ints_out,
                              int64_t *winners, int32_t simd)
{
    const int64_t w = p->width, h = p->height, n_s = p->n_slices;
    const int64_t stride = 2 * w + 2 * LSS_PAD;
    int64_t *ext;
    int64_t u, s, b, i;
    int vector = 0; /* the rows went through the vector path */
    if (w < 1 || h < 1 || n_s < 1 || n_s > LSS_MAX_SLICES) return -3;
    if (intensity && (intensity_type < LSS_F32 || intensity_type > LSS_I32)) return -2;
    ext = (int64_t *)malloc((size_t)(n_s * stride) * sizeof(int64_t));
    if (!ext) return -1;
    for (i = 0; i < n_s * stride; ++i) ext[i] = LSS_EMPTY;
#if LSS_AVX512
    if (simd && lss_avx512_ok()) {
        lss_rows t;
        t.stride = n_s;
        t.count = (int32_t *)malloc((size_t)(h * (n_s + 1)) * sizeof(int32_t));
        t.lo = (float *)malloc((size_t)(2 * h * n_s) * sizeof(float));
        t.qf = (uint8_t *)malloc((size_t)(2 * h * n_s));
        if (!t.count || !t.lo || !t.qf) {
            free(t.count), free(t.lo), free(t.qf), free(ext);
            return -1;
        }
        t.slice = t.count + h, t.hi = t.lo + h * n_s, t.qn = t.qf + h * n_s;
        for (u = 0; u < h; ++u) {
            int32_t live = 0;
            for (s = 0; s < n_s; ++s) {
                const float lo = p->lo[s * h + u], hi = p->hi[s * h + u];
                const int qf = p->q_per_pixel || ((p->qf[u] >> s) & 1u);
                const int qn = p->q_per_pixel || ((p->qn[u] >> s) & 1u);
                const int64_t j = u * n_s + live;
                if (!(lo <= hi) && !qf && !qn) continue;    /* the row never reaches slice s */
                t.slice[j] = (int32_t)s;
                t.lo[j] = lo, t.hi[j] = hi;
                t.qf[j] = !p->q_per_pixel && qf ? 0xFF : 0;
                t.qn[j] = !p->q_per_pixel && qn ? 0xFF : 0;
                ++live;
            }
            t.count[u] = live;
        }
        for (u = 0; u < h; ++u) {
            lss_row_avx512(p, &t, r, ext, u);
            lss_pixels(p, r, ext, u, w - w % 8, w);
        }
        free(t.count), free(t.lo), free(t.qf);
        vector = 1;
    }
#endif
    if (!vector)
        for (u = 0; u < h; ++u) lss_pixels(p, r, ext, u, 0, w);
    for (s = 0; s < n_s; ++s) {
        const int64_t *e = lss_ext(ext, p, s);
        const float inf_v = p->inf_value[s], fill_v = p->fill_value[s];
        for (b = 0; b < w; ++b) {
            const int64_t v = e[b] < e[b + w] ? e[b] : e[b + w];
            const int64_t j = s * w + b;
            const int64_t code = v >> 32;
            int64_t key;
            if (v == LSS_EMPTY) {
                ranges_out[j] = fill_v;
                if (intensity) ints_out[j] = 0.0f;
                if (winners) winners[j] = -1;
                continue;
            }
            if (code < LSS_CODE_NEG_INF) {
                const int32_t bits = (int32_t)code;
                memcpy(ranges_out + j, &bits, sizeof bits);
            } else if (code == LSS_CODE_NEG_INF) {
                ranges_out[j] = -INFINITY;
            } else if (code == LSS_CODE_POS_INF) {
                ranges_out[j] = inf_v;
            } else {
                ranges_out[j] = NAN;
            }
            key = v & 0xFFFFFFFF;
            if (winners) winners[j] = key;
            if (intensity)
                ints_out[j] = lss_intensity(intensity, intensity_type,
                                            p->key_to_pos ? p->key_to_pos[key] : key);
        }
    }
    free(ext);
    return 0;
}

/* ------------------------------------------------------------- (empty) Python module */

static struct PyModuleDef lss_module = {
    PyModuleDef_HEAD_INIT, "_slicekernel",
    "Compiled LidarScan -> LaserScan slices kernel (loaded with ctypes by converters.laserscan).",
    -1, NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__slicekernel(void)
{
    PyObject *module = PyModule_Create(&lss_module);
    if (module && PyModule_AddIntConstant(module, "ABI", LSS_ABI) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
