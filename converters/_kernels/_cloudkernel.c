/*
 * Optional compiled kernel of converters.pointcloud2 (LidarScan -> PointCloud2 hot loop).
 *
 * Plain C99 (plus SSE2 intrinsics where the compiler has them, e.g. every x86-64: one 4-lane
 * product and sum per point, the same roundings as the scalar code). The Python module part is
 * empty (it only makes the shared object an importable extension that setuptools builds and
 * installs, see setup.py); converters/pointcloud2.py loads the very same file with ctypes and
 * calls lsk_project(), which releases the GIL. Results must be bit-identical to the numpy path
 * of pointcloud2.py, so:
 *   - x = r * D + O is computed in float32 as a rounded product then a rounded sum: build with
 *     -ffp-contract=off (no fused multiply-add), never with -ffast-math;
 *   - invalid ranges become the canonical quiet NaN 0x7fc00000 (numpy's float32(nan)) and points
 *     are computed from it like every other (NaN * D + O propagates that NaN);
 *   - integer ranges: r = (float)raw, then r * mult (if asked), then r + offset (if asked), all
 *     float32; raw 0 = no return. Float ranges: valid iff 0 < r < +Inf, nothing else applied.
 *
 * lsk_project_rc() is the same job from the factored beam model (lidarscan/geometry.py,
 * beam_factors): per-beam and per-column factors instead of two per-pixel tables, so a point
 * costs a few float32 products on data that stays in the caches instead of 24 bytes of tables
 * streamed from memory. Its arithmetic is spelled out at lsk_rc_xyz; it rounds differently from
 * r * D + O (both are float32 evaluations of the same model, a few ulps apart). Built with
 * -fno-trapping-math so the branch-free selects vectorise, and, where the compiler and the
 * platform support it, as AVX-512 / AVX2 / baseline clones picked at load time: without
 * fused multiply-add every clone gives the same bits.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Bump with any change of lsk_project's signature or semantics (checked by pointcloud2.py). */
#define LSK_ABI 4

/* Source element types (the codes pointcloud2.py passes). */
enum {
    LSK_F32 = 0,
    LSK_F64 = 1,
    LSK_U8 = 2,
    LSK_U16 = 3,
    LSK_U32 = 4,
    LSK_I8 = 5,
    LSK_I16 = 6,
    LSK_I32 = 7
};

/* scale flags for integer ranges */
#define LSK_MULTIPLY 1
#define LSK_OFFSET 2

#define LSK_CHUNK 256
/* pixels per run of lsk_project_rc: 5 float buffers of it stay in L1 */
#define LSK_RC_CHUNK 1024

#if defined(_WIN32)
#define LSK_EXPORT __declspec(dllexport)
#else
#define LSK_EXPORT __attribute__((visibility("default")))
#endif

static float lsk_nan(void)
{
    const uint32_t bits = 0x7fc00000u;
    float value;
    memcpy(&value, &bits, sizeof value);
    return value;
}

/* dst[i] = (float)src[first + i] for i < count. Returns 0 on an unknown type. */
static int lsk_load_run(float *dst, const void *src, int32_t type, int64_t first, int64_t count)
{
    int64_t i;
#define LSK_RUN(T)                                                                 \
    do {                                                                           \
        const T *p = (const T *)src + first;                                       \
        for (i = 0; i < count; ++i) dst[i] = (float)p[i];                          \
    } while (0)
    switch (type) {
    case LSK_F32: LSK_RUN(float); return 1;
    case LSK_F64: LSK_RUN(double); return 1;
    case LSK_U8: LSK_RUN(uint8_t); return 1;
    case LSK_U16: LSK_RUN(uint16_t); return 1;
    case LSK_U32: LSK_RUN(uint32_t); return 1;
    case LSK_I8: LSK_RUN(int8_t); return 1;
    case LSK_I16: LSK_RUN(int16_t); return 1;
    case LSK_I32: LSK_RUN(int32_t); return 1;
    default: return 0;
    }
#undef LSK_RUN
}

/* dst[i] = (float)src[gather[start + i]] for i < count. Returns 0 on an unknown type. */
static int lsk_load_gather(float *dst, const void *src, int32_t type, const int64_t *gather,
                           int64_t start, int64_t count)
{
    const int64_t *g = gather + start;
    int64_t i;
#define LSK_GATHER(T)                                                              \
    do {                                                                           \
        const T *s = (const T *)src;                                               \
        for (i = 0; i < count; ++i) dst[i] = (float)s[g[i]];                       \
    } while (0)
    switch (type) {
    case LSK_F32: LSK_GATHER(float); return 1;
    case LSK_F64: LSK_GATHER(double); return 1;
    case LSK_U8: LSK_GATHER(uint8_t); return 1;
    case LSK_U16: LSK_GATHER(uint16_t); return 1;
    case LSK_U32: LSK_GATHER(uint32_t); return 1;
    case LSK_I8: LSK_GATHER(int8_t); return 1;
    case LSK_I16: LSK_GATHER(int16_t); return 1;
    case LSK_I32: LSK_GATHER(int32_t); return 1;
    default: return 0;
    }
#undef LSK_GATHER
}

/*
 * dst[i] = (float)src[index(start + i)] for i < count, where pixel j = u * width + c reads
 *   gather[j]                               (gather given),
 *   u * width + (c - roll[u]) mod width     (roll given, 0 <= roll[u] < width: row u rotated
 *                                            right by roll[u], as destaggering does),
 *   j                                       (neither).
 * Rolled rows are read as contiguous runs. Returns 0 on an unknown type.
 */
static int lsk_load(float *dst, const void *src, int32_t type, const int64_t *gather,
                    const int64_t *roll, int64_t width, int64_t start, int64_t count)
{
    int64_t j, end;
    if (gather) return lsk_load_gather(dst, src, type, gather, start, count);
    if (!roll) return lsk_load_run(dst, src, type, start, count);
    for (j = start, end = start + count; j < end;) {
        const int64_t u = j / width;
        const int64_t c = j - u * width;
        int64_t sc = c - roll[u];
        int64_t run = end - j;
        if (sc < 0) sc += width;
        if (run > width - c) run = width - c;
        if (run > width - sc) run = width - sc;
        if (!lsk_load_run(dst + (j - start), src, type, u * width + sc, run)) return 0;
        j += run;
    }
    return 1;
}

/* x, y, z = r * D + O (rounded product, then rounded sum) and the extra value of one point. */
static inline void lsk_point(char *point, int64_t xyz_offset, float r, const float *dj,
                             const float *oj, const float *extra, int64_t extra_offset)
{
    float xyz[3];
    xyz[0] = r * dj[0] + oj[0];
    xyz[1] = r * dj[1] + oj[1];
    xyz[2] = r * dj[2] + oj[2];
    memcpy(point + xyz_offset, xyz, sizeof xyz);
    if (extra) memcpy(point + extra_offset, extra, sizeof(float));
}

#if defined(__SSE2__) || defined(_M_X64) || (defined(_M_IX86_FP) && _M_IX86_FP >= 2)
#include <emmintrin.h>
#define LSK_SSE2 1
#else
#define LSK_SSE2 0
#endif

/* Extra-field placements, the point writers specialised on them. */
#define LSK_NO_EXTRA 0
#define LSK_EXTRA_APART 1 /* anywhere but right after z */
#define LSK_EXTRA_AFTER_Z 2 /* at xyz_offset + 12: x, y, z, extra = one 16-byte store */

#if defined(__GNUC__) || defined(__clang__)
#define LSK_INLINE static inline __attribute__((always_inline))
#else
#define LSK_INLINE static __forceinline
#endif

/*
 * Points of one chunk: rbuf (NaN = no return) / ebuf -> out. vec = how many leading pixels may
 * use the 4-lane form, which reads D and O one float past the pixel (never the last pixel of
 * the tables). SSE2 lane-wise products and sums round exactly like the scalar ones, so both
 * forms give the same bits. Returns the updated count of valid points.
 */
LSK_INLINE int64_t lsk_chunk(char *out, int64_t point_step, int64_t xyz_offset,
                             int64_t extra_offset, const float *rbuf, const float *ebuf,
                             const float *dj, const float *oj, int64_t first, int64_t count,
                             int64_t vec, int64_t valid, const int dense, const int mode)
{
    int64_t i;
    for (i = 0; i < count; ++i) {
        const float r = rbuf[i];
        char *point;
        if (dense) {
            if (r != r) continue;
            point = out + valid * point_step;
        } else {
            point = out + (first + i) * point_step;
        }
        valid += r == r;
#if LSK_SSE2
        if (i < vec) {
            const __m128 p = _mm_add_ps(_mm_mul_ps(_mm_set1_ps(r), _mm_loadu_ps(dj + 3 * i)),
                                        _mm_loadu_ps(oj + 3 * i));
            if (mode == LSK_EXTRA_AFTER_Z) {
                /* [x, y, z, e]: unpackhi -> [z, e, _, _], then [x, y] + [z, e] */
                const __m128 ze = _mm_unpackhi_ps(p, _mm_set1_ps(ebuf[i]));
                _mm_storeu_ps((float *)(void *)(point + xyz_offset),
                              _mm_shuffle_ps(p, ze, _MM_SHUFFLE(1, 0, 1, 0)));
            } else {
                const float z = _mm_cvtss_f32(_mm_movehl_ps(p, p));
                _mm_storel_epi64((__m128i *)(void *)(point + xyz_offset), _mm_castps_si128(p));
                memcpy(point + xyz_offset + 8, &z, sizeof z);
                if (mode == LSK_EXTRA_APART) memcpy(point + extra_offset, ebuf + i, sizeof(float));
            }
            continue;
        }
#else
        (void)vec;
#endif
        lsk_point(point, xyz_offset, r, dj + 3 * i, oj + 3 * i,
                  mode == LSK_NO_EXTRA ? NULL : ebuf + i, extra_offset);
    }
    return valid;
}

/* ranges of rbuf (as loaded) -> metres, canonical NaN where there is no return */
LSK_INLINE void lsk_metres(float *rbuf, int64_t count, int is_float, int32_t scale, float mult,
                           float offset)
{
    const float nan = lsk_nan();
    int64_t i;
    if (is_float) {
        for (i = 0; i < count; ++i) {
            const float r = rbuf[i];
            rbuf[i] = (r > 0.0f && r < INFINITY) ? r : nan;
        }
        return;
    }
    for (i = 0; i < count; ++i) {
        float r = rbuf[i];
        const int ok = r != 0.0f;
        if (scale & LSK_MULTIPLY) r = r * mult;
        if (scale & LSK_OFFSET) r = r + offset;
        rbuf[i] = ok ? r : nan;
    }
}

LSK_EXPORT int32_t lsk_abi(void) { return LSK_ABI; }

/*
 * Project pixels start .. start + n - 1 (grid = output order) into a PointCloud2 buffer.
 *
 *   out, point_step, xyz_offset: x, y, z float32 at out + p * point_step + xyz_offset (+4, +8),
 *       p = the pixel index (organized) or the running count of valid points (dense != 0);
 *       any alignment.
 *   range, range_type: the range image; pixel j reads range[index(j)] with gather / roll /
 *       width as lsk_load describes (the scan's column order -> the grid's).
 *   scale, mult, offset: LSK_MULTIPLY / LSK_OFFSET for integer ranges (see the file comment).
 *   d, o: direction / offset tables, float32 (pixels, 3) in grid order.
 *   extra, extra_type, extra_offset: optional channel (indexed like range) written as
 *       float32 at extra_offset (NULL: none).
 *   r_out: optional float32 ranges in grid order (NaN where invalid), r_out[j].
 *   dense: drop invalid pixels (points written consecutively from out).
 *
 * Returns the number of valid pixels, or -1 for an unknown type code.
 */
LSK_EXPORT int64_t lsk_project(char *out, int64_t point_step, int64_t xyz_offset, int64_t start,
                               int64_t n, const void *range, int32_t range_type,
                               const int64_t *gather, const int64_t *roll, int64_t width,
                               int32_t scale, float mult, float offset,
                               const float *d, const float *o, const void *extra,
                               int32_t extra_type, int64_t extra_offset, float *r_out,
                               int32_t dense)
{
    float rbuf[LSK_CHUNK];
    float ebuf[LSK_CHUNK];
    const int is_float = range_type == LSK_F32 || range_type == LSK_F64;
    int64_t valid = 0;
    int64_t done;

    for (done = 0; done < n; done += LSK_CHUNK) {
        const int64_t count = n - done < LSK_CHUNK ? n - done : LSK_CHUNK;
        const int64_t first = start + done;
        if (!lsk_load(rbuf, range, range_type, gather, roll, width, first, count)) return -1;
        if (extra && !lsk_load(ebuf, extra, extra_type, gather, roll, width, first, count))
            return -1;
        lsk_metres(rbuf, count, is_float, scale, mult, offset);
        if (r_out) memcpy(r_out + first, rbuf, (size_t)count * sizeof(float));
        {
            /* the 4-lane form reads one float past the pixel: not for the call's last one */
            const int64_t vec = done + count == n ? count - 1 : count;
            const float *dj = d + 3 * first;
            const float *oj = o + 3 * first;
            const int mode = !extra ? LSK_NO_EXTRA
                             : extra_offset == xyz_offset + 12 ? LSK_EXTRA_AFTER_Z
                                                               : LSK_EXTRA_APART;
#define LSK_CHUNK_CALL(DENSE, MODE)                                                             \
    valid = lsk_chunk(out, point_step, xyz_offset, extra_offset, rbuf, ebuf, dj, oj, first,     \
                      count, vec, valid, DENSE, MODE)
            if (dense) {
                if (mode == LSK_NO_EXTRA) LSK_CHUNK_CALL(1, LSK_NO_EXTRA);
                else if (mode == LSK_EXTRA_APART) LSK_CHUNK_CALL(1, LSK_EXTRA_APART);
                else LSK_CHUNK_CALL(1, LSK_EXTRA_AFTER_Z);
            } else {
                if (mode == LSK_NO_EXTRA) LSK_CHUNK_CALL(0, LSK_NO_EXTRA);
                else if (mode == LSK_EXTRA_APART) LSK_CHUNK_CALL(0, LSK_EXTRA_APART);
                else LSK_CHUNK_CALL(0, LSK_EXTRA_AFTER_Z);
            }
#undef LSK_CHUNK_CALL
        }
    }
    return valid;
}

/* ---------------------------------------------------------------- factored beam model */

#if defined(__x86_64__) && defined(__ELF__) && defined(__has_attribute)
#if __has_attribute(target_clones) && ((defined(__clang__) && __clang_major__ >= 14) || \
                                       (!defined(__clang__) && __GNUC__ >= 8))
#define LSK_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#endif
#endif
#ifndef LSK_CLONES
#define LSK_CLONES
#endif

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define LSK_AVX512 1
#include <immintrin.h>
#else
#define LSK_AVX512 0
#endif

/*
 * x, y, z of n pixels of beam row (o'x, o'y, o'z, d'x, d'y, d'z) and measurement columns
 * c0 .. c0 + n - 1 (factor planes a_x, b_x, a_y, b_y, a_z, b_z of `width` floats each, then the
 * constant g = R02, R12, R22, tx, ty, tz), float32, each product and sum rounded:
 *   q = o' + r * d'                                  (per axis: r * d' first)
 *   x = (a_x[c] * qx + b_x[c] * qy) + (g0 * qz + g3)  (y, z alike)
 * A NaN range (no return) gives NaN coordinates (its canonical NaN propagates).
 */
LSK_INLINE void lsk_rc_xyz(float *restrict x, float *restrict y, float *restrict z,
                           const float *restrict r, int64_t n, const float *restrict row,
                           const float *restrict cols, int64_t width, int64_t c0,
                           const float *restrict g)
{
    const float ox = row[0], oy = row[1], oz = row[2], dx = row[3], dy = row[4], dz = row[5];
    const float *ax = cols + c0, *bx = ax + width, *ay = bx + width, *by = ay + width;
    const float *az = by + width, *bz = az + width;
    int64_t i;
    for (i = 0; i < n; ++i) {
        const float qx = ox + r[i] * dx;
        const float qy = oy + r[i] * dy;
        const float qz = oz + r[i] * dz;
        x[i] = (ax[i] * qx + bx[i] * qy) + (g[0] * qz + g[3]);
        y[i] = (ay[i] * qx + by[i] * qy) + (g[1] * qz + g[4]);
        z[i] = (az[i] * qx + bz[i] * qy) + (g[2] * qz + g[5]);
    }
}

/*
 * Points of one run (x, y, z, e as separate arrays) into the cloud: organized at pixel
 * first + i, or dense (NaN points skipped) at the running count. Returns the updated count.
 */
LSK_INLINE int64_t lsk_rc_write(char *out, int64_t point_step, int64_t xyz_offset,
                                int64_t extra_offset, const float *x, const float *y,
                                const float *z, const float *e, int64_t first, int64_t count,
                                int64_t valid, int dense, int mode)
{
    int64_t i = 0;
    if (!dense) {
        char *base = out + first * point_step + xyz_offset;
        for (i = 0; i < count; ++i) valid += x[i] == x[i];
        i = 0;
#if LSK_SSE2
        if (mode == LSK_EXTRA_AFTER_Z) {
            /* x, y, z, e of 4 points -> 4 consecutive 16-byte stores (a 4 x 4 transpose) */
            for (; i + 4 <= count; i += 4) {
                __m128 p0 = _mm_loadu_ps(x + i), p1 = _mm_loadu_ps(y + i);
                __m128 p2 = _mm_loadu_ps(z + i), p3 = _mm_loadu_ps(e + i);
                _MM_TRANSPOSE4_PS(p0, p1, p2, p3);
                _mm_storeu_ps((float *)(void *)(base + i * point_step), p0);
                _mm_storeu_ps((float *)(void *)(base + (i + 1) * point_step), p1);
                _mm_storeu_ps((float *)(void *)(base + (i + 2) * point_step), p2);
                _mm_storeu_ps((float *)(void *)(base + (i + 3) * point_step), p3);
            }
        }
#endif
        for (; i < count; ++i) {
            float p[3];
            p[0] = x[i], p[1] = y[i], p[2] = z[i];
            memcpy(base + i * point_step, p, sizeof p);
            if (mode != LSK_NO_EXTRA) memcpy(base - xyz_offset + i * point_step + extra_offset,
                                             e + i, sizeof(float));
        }
        return valid;
    }
    for (i = 0; i < count; ++i) {
        char *point;
        float p[3];
        if (x[i] != x[i]) continue;
        point = out + valid * point_step;
        ++valid;
        p[0] = x[i], p[1] = y[i], p[2] = z[i];
        memcpy(point + xyz_offset, p, sizeof p);
        if (mode != LSK_NO_EXTRA) memcpy(point + extra_offset, e + i, sizeof(float));
    }
    return valid;
}

#if LSK_AVX512
/* 16 elements first + i .. of a source image as float32, converted like (float) in C */
__attribute__((target("avx512f"))) static inline __m512 lsk_v_load(const void *src,
                                                                   int32_t type, int64_t i)
{
    switch (type) {
    case LSK_F32: return _mm512_loadu_ps((const float *)src + i);
    case LSK_F64:
        return _mm512_castpd_ps(_mm512_insertf64x4(
            _mm512_castps_pd(_mm512_castps256_ps512(
                _mm512_cvtpd_ps(_mm512_loadu_pd((const double *)src + i)))),
            _mm256_castps_pd(_mm512_cvtpd_ps(_mm512_loadu_pd((const double *)src + i + 8))),
            1));
    case LSK_U8:
        return _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(
            _mm_loadu_si128((const __m128i *)(const void *)((const uint8_t *)src + i))));
    case LSK_U16:
        return _mm512_cvtepi32_ps(_mm512_cvtepu16_epi32(
            _mm256_loadu_si256((const __m256i *)(const void *)((const uint16_t *)src + i))));
    case LSK_U32:
        return _mm512_cvtepu32_ps(
            _mm512_loadu_si512((const void *)((const uint32_t *)src + i)));
    case LSK_I8:
        return _mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(
            _mm_loadu_si128((const __m128i *)(const void *)((const int8_t *)src + i))));
    case LSK_I16:
        return _mm512_cvtepi32_ps(_mm512_cvtepi16_epi32(
            _mm256_loadu_si256((const __m256i *)(const void *)((const int16_t *)src + i))));
    default: /* LSK_I32 (types are checked before) */
        return _mm512_cvtepi32_ps(_mm512_loadu_si512((const void *)((const int32_t *)src + i)));
    }
}

/*
 * The organized x, y, z, e (extra right after z) case of a run, 16 pixels at a time with
 * AVX-512, straight from the source images (range and extra start at their element `first`,
 * contiguous): lsk_load + lsk_metres + lsk_rc_xyz lane by lane (same conversions, operations
 * and order, no fused multiply-add, so the same bits), then a 4 x 16 transpose into four
 * 64-byte stores. Handles the first n - n % 16 pixels; returns how many of them are valid.
 */
__attribute__((target("avx512f"))) static int64_t lsk_rc_avx512(
    char *base, int64_t point_step, const void *range, int32_t range_type, const void *extra,
    int32_t extra_type, int64_t first, int32_t scale, float mult, float offset, float *r_out,
    int64_t n, const float *row, const float *cols, int64_t width, int64_t c0, const float *g)
{
    const int is_float = range_type == LSK_F32 || range_type == LSK_F64;
    const __m512 nan = _mm512_set1_ps(lsk_nan()), zero = _mm512_setzero_ps();
    const __m512 inf = _mm512_set1_ps(INFINITY);
    const __m512 vmult = _mm512_set1_ps(mult), voffset = _mm512_set1_ps(offset);
    const __m512 ox = _mm512_set1_ps(row[0]), oy = _mm512_set1_ps(row[1]);
    const __m512 oz = _mm512_set1_ps(row[2]), dx = _mm512_set1_ps(row[3]);
    const __m512 dy = _mm512_set1_ps(row[4]), dz = _mm512_set1_ps(row[5]);
    const __m512 g0 = _mm512_set1_ps(g[0]), g1 = _mm512_set1_ps(g[1]);
    const __m512 g2 = _mm512_set1_ps(g[2]), g3 = _mm512_set1_ps(g[3]);
    const __m512 g4 = _mm512_set1_ps(g[4]), g5 = _mm512_set1_ps(g[5]);
    const float *ax = cols + c0, *bx = ax + width, *ay = bx + width, *by = ay + width;
    const float *az = by + width, *bz = az + width;
    int64_t valid = 0, i;
    for (i = 0; i + 16 <= n; i += 16) {
        __m512 rv = lsk_v_load(range, range_type, first + i);
        if (is_float) {
            const __mmask16 ok = _mm512_cmp_ps_mask(rv, zero, _CMP_GT_OQ)
                                 & _mm512_cmp_ps_mask(rv, inf, _CMP_LT_OQ);
            rv = _mm512_mask_blend_ps(ok, nan, rv);
        } else {
            const __mmask16 ok = _mm512_cmp_ps_mask(rv, zero, _CMP_NEQ_UQ);
            if (scale & LSK_MULTIPLY) rv = _mm512_mul_ps(rv, vmult);
            if (scale & LSK_OFFSET) rv = _mm512_add_ps(rv, voffset);
            rv = _mm512_mask_blend_ps(ok, nan, rv);
        }
        if (r_out) _mm512_storeu_ps(r_out + first + i, rv);
        const __m512 qx = _mm512_add_ps(ox, _mm512_mul_ps(rv, dx));
        const __m512 qy = _mm512_add_ps(oy, _mm512_mul_ps(rv, dy));
        const __m512 qz = _mm512_add_ps(oz, _mm512_mul_ps(rv, dz));
#define LSK_AXIS(A, B, G, T)                                                                   \
    _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(_mm512_loadu_ps(A + i), qx),                    \
                                _mm512_mul_ps(_mm512_loadu_ps(B + i), qy)),                   \
                  _mm512_add_ps(_mm512_mul_ps(G, qz), T))
        const __m512 x = LSK_AXIS(ax, bx, g0, g3);
        const __m512 y = LSK_AXIS(ay, by, g1, g4);
        const __m512 z = LSK_AXIS(az, bz, g2, g5);
#undef LSK_AXIS
        const __m512 ev = lsk_v_load(extra, extra_type, first + i);
        /* per 128-bit lane: [x y z e] of points k, k + 4, k + 8, k + 12 in register k */
        const __m512 xy_lo = _mm512_unpacklo_ps(x, y), xy_hi = _mm512_unpackhi_ps(x, y);
        const __m512 ze_lo = _mm512_unpacklo_ps(z, ev), ze_hi = _mm512_unpackhi_ps(z, ev);
        const __m512 p0 = _mm512_shuffle_ps(xy_lo, ze_lo, _MM_SHUFFLE(1, 0, 1, 0));
        const __m512 p1 = _mm512_shuffle_ps(xy_lo, ze_lo, _MM_SHUFFLE(3, 2, 3, 2));
        const __m512 p2 = _mm512_shuffle_ps(xy_hi, ze_hi, _MM_SHUFFLE(1, 0, 1, 0));
        const __m512 p3 = _mm512_shuffle_ps(xy_hi, ze_hi, _MM_SHUFFLE(3, 2, 3, 2));
        /* then a 4 x 4 transpose of 128-bit lanes: points 4j .. 4j + 3 in output j */
        const __m512 a = _mm512_shuffle_f32x4(p0, p1, _MM_SHUFFLE(1, 0, 1, 0));
        const __m512 b = _mm512_shuffle_f32x4(p0, p1, _MM_SHUFFLE(3, 2, 3, 2));
        const __m512 c = _mm512_shuffle_f32x4(p2, p3, _MM_SHUFFLE(1, 0, 1, 0));
        const __m512 d = _mm512_shuffle_f32x4(p2, p3, _MM_SHUFFLE(3, 2, 3, 2));
        char *out = base + i * point_step;
        if (point_step == 16) {
            _mm512_storeu_ps(out, _mm512_shuffle_f32x4(a, c, _MM_SHUFFLE(2, 0, 2, 0)));
            _mm512_storeu_ps(out + 64, _mm512_shuffle_f32x4(a, c, _MM_SHUFFLE(3, 1, 3, 1)));
            _mm512_storeu_ps(out + 128, _mm512_shuffle_f32x4(b, d, _MM_SHUFFLE(2, 0, 2, 0)));
            _mm512_storeu_ps(out + 192, _mm512_shuffle_f32x4(b, d, _MM_SHUFFLE(3, 1, 3, 1)));
        } else {
            /* wider points: one 16-byte store per point */
            float tmp[64];
            int k;
            _mm512_storeu_ps(tmp, _mm512_shuffle_f32x4(a, c, _MM_SHUFFLE(2, 0, 2, 0)));
            _mm512_storeu_ps(tmp + 16, _mm512_shuffle_f32x4(a, c, _MM_SHUFFLE(3, 1, 3, 1)));
            _mm512_storeu_ps(tmp + 32, _mm512_shuffle_f32x4(b, d, _MM_SHUFFLE(2, 0, 2, 0)));
            _mm512_storeu_ps(tmp + 48, _mm512_shuffle_f32x4(b, d, _MM_SHUFFLE(3, 1, 3, 1)));
            for (k = 0; k < 16; ++k) memcpy(out + k * point_step, tmp + 4 * k, 16);
        }
        valid += __builtin_popcount((unsigned)_mm512_cmp_ps_mask(rv, rv, _CMP_ORD_Q));
    }
    return valid;
}

static int lsk_avx512_ok(void)
{
    static int known = -1;
    if (known < 0) known = __builtin_cpu_supports("avx512f") ? 1 : 0;
    return known;
}
#endif

/* Whether lsk_project_rc's AVX-512 path runs on this CPU when called with simd = 1. */
LSK_EXPORT int32_t lsk_vectorised(void)
{
#if LSK_AVX512
    return lsk_avx512_ok();
#else
    return 0;
#endif
}

/* One run: pixels first .. first + count - 1 of one grid row, measurement columns c0 .. */
LSK_CLONES
static int64_t lsk_rc_run(char *out, int64_t point_step, int64_t xyz_offset, int64_t first,
                          int64_t count, const void *range, int32_t range_type,
                          int64_t src_first, int32_t scale, float mult, float offset,
                          const float *row, const float *cols, int64_t width, int64_t c0,
                          const float *g, const void *extra, int32_t extra_type,
                          int64_t extra_offset, float *r_out, int32_t dense, int32_t simd,
                          int64_t valid)
{
    float rbuf[LSK_RC_CHUNK], ebuf[LSK_RC_CHUNK], x[LSK_RC_CHUNK], y[LSK_RC_CHUNK];
    float z[LSK_RC_CHUNK];
    const int mode = !extra ? LSK_NO_EXTRA
                     : extra_offset == xyz_offset + 12 ? LSK_EXTRA_AFTER_Z : LSK_EXTRA_APART;
#if LSK_AVX512
    if (simd && !dense && mode == LSK_EXTRA_AFTER_Z && count >= 16 && lsk_avx512_ok()) {
        const int64_t done = count - count % 16;
        /* the 16-pixel path reads the sources itself (no staging buffers) */
        valid += lsk_rc_avx512(out + first * point_step + xyz_offset, point_step, range,
                               range_type, extra, extra_type, src_first, scale, mult, offset,
                               r_out ? r_out + (first - src_first) : NULL, done, row, cols,
                               width, c0, g);
        first += done, src_first += done, count -= done, c0 += done;
        if (!count) return valid;
    }
#endif
    if (!lsk_load_run(rbuf, range, range_type, src_first, count)) return -1;
    if (extra && !lsk_load_run(ebuf, extra, extra_type, src_first, count)) return -1;
    lsk_metres(rbuf, count, range_type == LSK_F32 || range_type == LSK_F64, scale, mult, offset);
    if (r_out) memcpy(r_out + first, rbuf, (size_t)count * sizeof(float));
    lsk_rc_xyz(x, y, z, rbuf, count, row, cols, width, c0, g);
    if (dense) return lsk_rc_write(out, point_step, xyz_offset, extra_offset, x, y, z, ebuf,
                                   first, count, valid, 1, mode);
    return lsk_rc_write(out, point_step, xyz_offset, extra_offset, x, y, z, ebuf, first, count,
                        valid, 0, mode);
}

/*
 * lsk_project with the factored model: arguments as lsk_project, except (gather not supported)
 *   rows: (H, 6) float32 beam factors o', d' (lidarscan.geometry.beam_factors);
 *   cols: (6, width) float32 column factors, indexed by measurement column;
 *   g: (6,) float32 constant;
 *   colshift: per-row 0 <= colshift[u] < width: grid column v of row u is measurement column
 *       (v - colshift[u]) mod width (destaggered grid), or NULL (grid in measurement order).
 * Returns the number of valid pixels, or -1 for an unknown type code.
 */
LSK_EXPORT int64_t lsk_project_rc(char *out, int64_t point_step, int64_t xyz_offset,
                                  int64_t start, int64_t n, const void *range,
                                  int32_t range_type, const int64_t *roll,
                                  const int64_t *colshift, int64_t width, int32_t scale,
                                  float mult, float offset, const float *rows,
                                  const float *cols, const float *g, const void *extra,
                                  int32_t extra_type, int64_t extra_offset, float *r_out,
                                  int32_t dense, int32_t simd)
{
    int64_t valid = 0;
    int64_t j = start;
    const int64_t end = start + n;
    while (j < end) {
        const int64_t u = j / width;
        const int64_t v = j - u * width;
        int64_t c = colshift ? v - colshift[u] : v;
        int64_t sc = roll ? v - roll[u] : v;            /* the source image's column */
        int64_t run = end - j;
        if (c < 0) c += width;
        if (sc < 0) sc += width;
        if (run > width - v) run = width - v;          /* stay in the row */
        if (run > width - c) run = width - c;          /* contiguous measurement columns */
        if (run > width - sc) run = width - sc;        /* contiguous source pixels */
        if (run > LSK_RC_CHUNK) run = LSK_RC_CHUNK;
        valid = lsk_rc_run(out, point_step, xyz_offset, j, run, range, range_type,
                           u * width + sc, scale, mult, offset, rows + 6 * u, cols, width, c, g,
                           extra, extra_type, extra_offset, r_out, dense, simd, valid);
        if (valid < 0) return -1;
        j += run;
    }
    return valid;
}

/* ------------------------------------------------------------- (empty) Python module */

static struct PyModuleDef lsk_module = {
    PyModuleDef_HEAD_INIT, "_cloudkernel",
    "Compiled LidarScan -> PointCloud2 kernel (loaded with ctypes by converters.pointcloud2).",
    -1, NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__cloudkernel(void)
{
    PyObject *module = PyModule_Create(&lsk_module);
    if (module && PyModule_AddIntConstant(module, "ABI", LSK_ABI) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
