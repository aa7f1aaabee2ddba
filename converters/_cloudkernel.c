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
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

/* Bump with any change of lsk_project's signature or semantics (checked by pointcloud2.py). */
#define LSK_ABI 2

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
    const float nan = lsk_nan();
    const int is_float = range_type == LSK_F32 || range_type == LSK_F64;
    int64_t valid = 0;
    int64_t done;

    for (done = 0; done < n; done += LSK_CHUNK) {
        const int64_t count = n - done < LSK_CHUNK ? n - done : LSK_CHUNK;
        const int64_t first = start + done;
        int64_t i;
        if (!lsk_load(rbuf, range, range_type, gather, roll, width, first, count)) return -1;
        if (extra && !lsk_load(ebuf, extra, extra_type, gather, roll, width, first, count))
            return -1;
        if (is_float) {
            for (i = 0; i < count; ++i) {
                const float r = rbuf[i];
                rbuf[i] = (r > 0.0f && r < INFINITY) ? r : nan;
            }
        } else {
            for (i = 0; i < count; ++i) {
                float r = rbuf[i];
                const int ok = r != 0.0f;
                if (scale & LSK_MULTIPLY) r = r * mult;
                if (scale & LSK_OFFSET) r = r + offset;
                rbuf[i] = ok ? r : nan;
            }
        }
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
