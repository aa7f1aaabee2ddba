/*
 * Optional compiled kernel of converters.velodyne: packet bytes -> a rotation's channel views,
 * and the per-packet header checks, in one pass over the packets each.
 *
 * vdk_fill writes what the numpy reference of converters/velodyne/packets.py computes in several
 * passes (_fill_numpy: the range / intensity grids; _azimuths_numpy and _nebula_azimuths: the
 * per-pixel `azimuth` channel, Nebula's angle) straight into the channel views of a
 * lidarscan.scan.ScanBuffer, with the same integer results (tests/test_velodyne_golden.py
 * compares the digests of both paths). Per packet: Nebula's block walk (base azimuth and gap
 * of each block), then the angle of every point slot of the packet (32 * block + k) in a
 * contiguous loop over the slots (the compiler vectorises it where the CPU has SSE4.1 / AVX:
 * target clones), then for each firing sequence of the packet and each row the distance and
 * reflectivity of each return slot, written at (row, column) with the slot's angle (through
 * small column tiles: see vdk_fill_tiles, the portable path).
 *
 * One firing sequence per packet (a dual-return VLS-128: one column per packet) has a second
 * path on x86-64 CPUs with AVX2 (vdk_fill_one, chosen at run time unless the caller passes
 * simd = 0, as converters/_kernels/velodyne.py does for LIDARSCAN_VELODYNE_SIMD=0): tiles of
 * VDK_T packets are gathered slot-major (each block's 3-byte points split with byte shuffles,
 * then 8 x 8 transposes across the packets), the angles are computed eight packets per vector
 * (the same float32 / float64 operations on the same values), and the row permutation happens
 * in the row copies (32-byte stores, the identical-pair rule as a vector blend; the output
 * lines of the tiles ahead prefetched: 768 row streams are more than the hardware prefetchers
 * follow). Both paths write the same bytes (tests/test_velokernel.py).
 *
 * Arithmetic, exactly as the reference (build with -ffp-contract=off, never -ffast-math):
 *   term  = gap * f                      (VLP-16: (gap * f) / 110.592f)    float32
 *   value = (double)(float)(base + term) - rotation                        float64
 *   value = (double)(float)value; if value < 0: value = (double)(float)(value + 36000.0)
 *   cw    = (int64)floor(value + 0.5) & 0xFFFF, minus 36000 once if >= 36000
 *   angle = cw ? 36000 - cw : 0                                 (counter-clockwise 0.01 deg)
 * The caller guarantees |rotation| < VDK_MAX_ROTATION = 1e6 (Python: MAX_ROTATION), so that
 * every value after the subtraction is below 2^22 in magnitude (base < 65536, |term| < 2^17)
 * and the steps after it are exact in float32 (vdk_angles).
 *
 * converters/_kernels/velodyne.py loads this shared object with ctypes (which releases the GIL
 * during the calls). The kernel reads packets through a table of their addresses (no copy of
 * separate payloads into one buffer): vdk_good (header checks), vdk_words (header words) and
 * vdk_fill. The module's one Python function, table(), builds that table from a list of
 * (stamp, bytes) pairs in one pass (converters.velodyne.decode_packets).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Bump with any change of a function's signature or semantics. */
#define VDK_ABI 3

#define VDK_PACKET 1206
#define VDK_BLOCKS 12
#define VDK_SLOTS (VDK_BLOCKS * 32)
#ifndef VDK_TILE
#define VDK_TILE 32 /* columns per tile */
#endif
#define VDK_ROWS 128 /* most rows (lasers) */
#ifndef VDK_TILE_PF
#define VDK_TILE_PF (2 * VDK_TILE) /* columns ahead whose output lines are prefetched */
#endif
#define VDK_AHEAD 4 /* packets prefetched ahead */
/* bytes of n elements: a constant for a whole tile (an inlined copy) */
#define VDK_BYTES(n, type) ((n) == VDK_TILE ? VDK_TILE * sizeof(type) : (size_t)(n) * sizeof(type))

#if defined(_WIN32)
#define VDK_EXPORT __declspec(dllexport)
#else
#define VDK_EXPORT __attribute__((visibility("default")))
#endif

#if defined(__GNUC__) || defined(__clang__)
#define VDK_INLINE static inline __attribute__((always_inline))
#define VDK_PREFETCH(p) __builtin_prefetch(p)
#define VDK_PREFETCH_W(p) __builtin_prefetch(p, 1)
#else
#define VDK_INLINE static inline
#define VDK_PREFETCH(p) ((void)(p))
#define VDK_PREFETCH_W(p) ((void)(p))
#endif

#if defined(__x86_64__) && defined(__ELF__) && defined(__has_attribute)
#if __has_attribute(target_clones) && ((defined(__clang__) && __clang_major__ >= 14) || \
                                       (!defined(__clang__) && __GNUC__ >= 8))
#define VDK_CLONES __attribute__((target_clones("avx", "sse4.1", "default")))
#endif
#endif
#ifndef VDK_CLONES
#define VDK_CLONES
#endif

VDK_EXPORT int32_t vdk_abi(void) { return VDK_ABI; }

/* Little-endian u16 at byte o of a packet. */
VDK_INLINE int64_t vdk_u16(const uint8_t *pkt, int64_t o)
{
    return (int64_t)pkt[o] | ((int64_t)pkt[o + 1] << 8);
}

/* Little-endian u32 at p (unaligned). */
VDK_INLINE uint32_t vdk_u32(const uint8_t *p)
{
    uint32_t v;
    memcpy(&v, p, sizeof v);
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_BIG_ENDIAN__
    v = __builtin_bswap32(v);
#endif
    return v;
}

/*
 * The header checks of PacketDecoder over n packets given by address (pkts[p]: the 1206 bytes of
 * packet p): good[p] = 1 for each packet whose factory bytes equal `key` (product << 8 | return
 * mode) and whose first `used` blocks each have the flag 0xFF, flags[b] and an azimuth below
 * 36000; good[p] of the other packets is left as it is. Returns the number of packets set.
 */
VDK_EXPORT int64_t vdk_good(const uint8_t *const *pkts, int64_t n, int32_t key,
                            const uint8_t *flags, int64_t used, uint8_t *good)
{
    int64_t set = 0;
    for (int64_t p = 0; p < n; ++p) {
        const uint8_t *pkt = pkts[p];
        if (p + VDK_AHEAD < n)                  /* scattered packets: help the prefetcher */
            for (int64_t b = 0; b < used; ++b)
                VDK_PREFETCH(pkts[p + VDK_AHEAD] + 100 * b);
        int bad = (((int32_t)pkt[1205] << 8) | pkt[1204]) != key;
        for (int64_t b = 0; b < used; ++b) {
            const uint8_t *head = pkt + 100 * b;
            bad |= (head[0] != 0xFF) | (head[1] != flags[b]) | (vdk_u16(head, 2) >= 36000);
        }
        if (!bad) {
            good[p] = 1;
            ++set;
        }
    }
    return set;
}

/* The k little-endian u16 words at[0..k-1] (word w: bytes 2w, 2w + 1) of n packets given by
 * address, into out (n, k). */
VDK_EXPORT void vdk_words(const uint8_t *const *pkts, int64_t n, const int64_t *at, int64_t k,
                          uint16_t *out)
{
    for (int64_t p = 0; p < n; ++p, out += k)
        for (int64_t i = 0; i < k; ++i)
            out[i] = (uint16_t)vdk_u16(pkts[p], 2 * at[i]);
}

/* Nebula's block walk of one packet: the float32 base azimuth and gap of its first n_blocks
 * blocks (see _nebula_azimuths in converters/velodyne/packets.py). */
VDK_INLINE void vdk_blocks(const uint8_t *pkt, int64_t family, int64_t dual, int64_t n_blocks,
                           float *base, float *gap)
{
    const int64_t step = dual ? 2 : 1;
    const int64_t zero = VDK_BLOCKS - (family == 0 ? 1 : 4) * (dual ? 1 : 0) - 1;
    int64_t ahead = 0;
    float last = 0.0f;
    for (int64_t i = 0; i < n_blocks; ++i) {
        const int64_t raw = i == 0 ? vdk_u16(pkt, 2) : ahead;
        float g;
        if (i < VDK_BLOCKS - step) {
            ahead = vdk_u16(pkt, 100 * (i + step) + 2);
            const int64_t diff = 36000 + ahead - raw;
            const int64_t mod = llabs(diff) % 36000;              /* C's %: sign of diff */
            last = (float)(diff >= 0 ? mod : -mod);
            g = last;
        } else {
            g = i == zero ? 0.0f : last;
        }
        base[i] = (float)raw;
        gap[i] = family == 1 ? g * (float)2.304 / (float)55.296 : g;
    }
}

/* The counter-clockwise angle (0.01 deg) of the 32 slots of one block. After the float64
 * subtraction every value is a float32 below 2^22 in magnitude (|rotation| < VDK_MAX_ROTATION),
 * so the reference's float64 steps (the wrap's (float)(value + 36000.0), value + 0.5, floor)
 * are exact in float32 and give the same integers. */
VDK_CLONES static void vdk_angles(float base, float gap, int64_t vlp16, const float *factor,
                                  const double *rotation, uint16_t *out)
{
    const float scale = (float)110.592;
    for (int k = 0; k < 32; ++k) {
        const float term = vlp16 ? (gap * factor[k]) / scale : gap * factor[k];
        float value = (float)((double)(base + term) - rotation[k]);
        value = value < 0.0f ? value + 36000.0f : value;
        int32_t cw = (int32_t)floorf(value + 0.5f) & 0xFFFF;
        cw = cw >= 36000 ? cw - 36000 : cw;
        out[k] = (uint16_t)(cw ? 36000 - cw : 0);
    }
}

/*
 * The portable path of vdk_fill (same arguments, same result; see there): the columns are taken
 * in tiles of VDK_TILE; a tile is first gathered column by column into small row-major buffers
 * (L1/L2; the distance and reflectivity of a point as one unaligned 32-bit load, the
 * identical-pair rule applied there), then each of their rows is copied into the views with
 * contiguous stores; the packets a few ahead are prefetched. Returns 0 or -2 as vdk_fill (which
 * has checked the shape; count > 0).
 */
static int64_t vdk_fill_tiles(const uint8_t *const *pkts, int64_t begin, int64_t count,
                              int64_t column, int64_t returns, int64_t seqs, int64_t rows,
                              int64_t width,
                              const int32_t *offsets, const int16_t *slots, const float *factor,
                              const double *rotation, int64_t family, int64_t dual,
                              int64_t n_blocks, uint16_t *r0, uint8_t *i0, uint16_t *r1,
                              uint8_t *i1, uint16_t *a0, uint16_t *a1)
{
    uint16_t angle[VDK_SLOTS] = {0};
    float base[VDK_BLOCKS], gap[VDK_BLOCKS];
    uint16_t (*tr)[VDK_ROWS][VDK_TILE] = malloc(sizeof(uint16_t[2][VDK_ROWS][VDK_TILE]) * 2 +
                                                sizeof(uint8_t[2][VDK_ROWS][VDK_TILE]));
    if (!tr) return -2;
    uint16_t (*ta)[VDK_ROWS][VDK_TILE] = tr + 2;
    uint8_t (*ti)[VDK_ROWS][VDK_TILE] = (uint8_t (*)[VDK_ROWS][VDK_TILE])(ta + 2);
    uint16_t *const rv[2] = {r0, r1}, *const av[2] = {a0, a1};
    uint8_t *const iv[2] = {i0, i1};
    int64_t packet = -1;
    const int64_t end = (begin + count - 1) / seqs + 1;     /* packets read: 0 .. end - 1 */
    for (int64_t c0 = 0; c0 < count; c0 += VDK_TILE) {
        const int64_t n = count - c0 < VDK_TILE ? count - c0 : VDK_TILE;
        for (int64_t j = 0; j < n; ++j) {                     /* gather the tile's columns */
            const int64_t q = begin + c0 + j, p = q / seqs, s = q % seqs;
            const uint8_t *pkt = pkts[p];
            if (p != packet && p + VDK_AHEAD < end)
                for (int64_t b = 0; b < VDK_PACKET; b += 64)  /* the packets ahead */
                    VDK_PREFETCH(pkts[p + VDK_AHEAD] + b);
            if (a0 && p != packet) {
                vdk_blocks(pkt, family, dual, n_blocks, base, gap);
                for (int64_t b = 0; b < n_blocks; ++b)
                    vdk_angles(base[b], gap[b], family == 0, factor + 32 * b,
                               rotation + 32 * b, angle + 32 * b);
            }
            packet = p;
            const int32_t *off0 = offsets + s * rows, *off1 = off0 + seqs * rows;
            const int16_t *slot0 = slots + s * rows, *slot1 = slot0 + seqs * rows;
            if (returns == 1) {
                for (int64_t h = 0; h < rows; ++h) {   /* distance, reflectivity: one load */
                    const uint32_t v = vdk_u32(pkt + off0[h]);
                    tr[0][h][j] = (uint16_t)v;
                    ti[0][h][j] = (uint8_t)(v >> 16);
                    if (a0) ta[0][h][j] = angle[slot0[h]];
                }
            } else if (a0) {
                for (int64_t h = 0; h < rows; ++h) {
                    const uint32_t v = vdk_u32(pkt + off0[h]), w = vdk_u32(pkt + off1[h]);
                    const uint16_t last = angle[slot1[h]];
                    tr[0][h][j] = (uint16_t)v;
                    ti[0][h][j] = (uint8_t)(v >> 16);
                    tr[1][h][j] = (uint16_t)w;
                    ti[1][h][j] = (uint8_t)(w >> 16);
                    ta[1][h][j] = last;
                    /* an identical pair: the last return's angle */
                    ta[0][h][j] = (uint16_t)v == (uint16_t)w ? last : angle[slot0[h]];
                }
            } else {
                for (int64_t h = 0; h < rows; ++h) {
                    const uint32_t v = vdk_u32(pkt + off0[h]), w = vdk_u32(pkt + off1[h]);
                    tr[0][h][j] = (uint16_t)v;
                    ti[0][h][j] = (uint8_t)(v >> 16);
                    tr[1][h][j] = (uint16_t)w;
                    ti[1][h][j] = (uint8_t)(w >> 16);
                }
            }
        }
        const int64_t col = column + c0;
        const int ahead = col + n + VDK_TILE_PF <= width;     /* the lines of the tiles ahead */
        for (int64_t r = 0; r < returns; ++r)                  /* copy the rows out */
            for (int64_t h = 0; h < rows; ++h) {
                memcpy(rv[r] + h * width + col, tr[r][h], VDK_BYTES(n, uint16_t));
                memcpy(iv[r] + h * width + col, ti[r][h], VDK_BYTES(n, uint8_t));
                if (ahead) {
                    VDK_PREFETCH_W(rv[r] + h * width + col + VDK_TILE_PF);
                    VDK_PREFETCH_W(iv[r] + h * width + col + VDK_TILE_PF);
                }
            }
        if (a0)
            for (int64_t r = 0; r < returns; ++r)
                for (int64_t h = 0; h < rows; ++h) {
                    memcpy(av[r] + h * width + col, ta[r][h], VDK_BYTES(n, uint16_t));
                    if (ahead) VDK_PREFETCH_W(av[r] + h * width + col + VDK_TILE_PF);
                }
    }
    free(tr);
    return 0;
}

/* ------------------------------------------------ one firing sequence per packet (VLS-128 dual) */

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__)) && \
    defined(__has_attribute) && !defined(VDK_NO_SIMD)      /* -DVDK_NO_SIMD: portable only */
#if __has_attribute(target)
#define VDK_SIMD 1
#endif
#endif

#ifdef VDK_SIMD
#include <immintrin.h>

#ifndef VDK_T
#define VDK_T 16 /* packets (columns) per tile of the one-sequence path: a multiple of 16 */
#endif
#ifndef VDK_PF
#define VDK_PF (4 * VDK_T) /* columns ahead whose output lines are prefetched (for writing) */
#endif
#define VDK_AVX2 __attribute__((target("avx2")))
#define VDK_AVX2_INLINE static inline __attribute__((target("avx2"), always_inline))

/* v[j] = 8 u16 of packet j (points 0..7) -> v[k] = point k of packets 0..7. */
VDK_AVX2_INLINE void vdk_t16(__m128i v[8])
{
    __m128i a[8], b[8];
    for (int i = 0; i < 4; ++i) {
        a[2 * i] = _mm_unpacklo_epi16(v[2 * i], v[2 * i + 1]);
        a[2 * i + 1] = _mm_unpackhi_epi16(v[2 * i], v[2 * i + 1]);
    }
    for (int i = 0; i < 2; ++i) {
        b[4 * i] = _mm_unpacklo_epi32(a[4 * i], a[4 * i + 2]);       /* points 0, 1 */
        b[4 * i + 1] = _mm_unpackhi_epi32(a[4 * i], a[4 * i + 2]);   /* 2, 3 */
        b[4 * i + 2] = _mm_unpacklo_epi32(a[4 * i + 1], a[4 * i + 3]); /* 4, 5 */
        b[4 * i + 3] = _mm_unpackhi_epi32(a[4 * i + 1], a[4 * i + 3]); /* 6, 7 */
    }
    for (int i = 0; i < 4; ++i) {
        v[2 * i] = _mm_unpacklo_epi64(b[i], b[4 + i]);
        v[2 * i + 1] = _mm_unpackhi_epi64(b[i], b[4 + i]);
    }
}

/*
 * Gather one tile of VDK_T packets (one column each; tile[j]: packet j's bytes) into slot-major
 * rows: D[slot][j] distance, I[slot][j] reflectivity of point slot `slot` (32 * block + k,
 * blocks 0..nb-1) of packet j, and, when `angles`, A[slot][j] its counter-clockwise angle (the
 * arithmetic of vdk_angles, eight packets per vector: the same operations on the same values,
 * so the same integers).
 */
VDK_AVX2 static void vdk_tile(const uint8_t *const *tile, int64_t nb, int angles, int64_t family,
                              int64_t dual, int64_t n_blocks, const float *factor,
                              const double *rotation, const int64_t *twin,
                              uint16_t (*D)[VDK_T], uint8_t (*I)[VDK_T], uint16_t (*A)[VDK_T])
{
    /* 16 bytes at point 4i: distance lo/hi of points 0..3, then their reflectivities */
    const __m128i split = _mm_setr_epi8(0, 1, 3, 4, 6, 7, 9, 10, 2, 5, 8, 11, -1, -1, -1, -1);
    for (int g = 0; g < VDK_T; g += 8) {
        const uint8_t *const *pkt = tile + g;
        for (int64_t b = 0; b < nb; ++b)
            for (int k8 = 0; k8 < 32; k8 += 8) {
                __m128i d[8], r[8];
                const int64_t at = 100 * b + 4 + 3 * k8;
                for (int j = 0; j < 8; ++j) {
                    const uint8_t *q = pkt[j] + at;
                    const __m128i lo = _mm_shuffle_epi8(_mm_loadu_si128((const __m128i *)q), split);
                    const __m128i hi =
                        _mm_shuffle_epi8(_mm_loadu_si128((const __m128i *)(q + 12)), split);
                    d[j] = _mm_unpacklo_epi64(lo, hi);          /* distances of points 0..7 */
                    r[j] = _mm_unpackhi_epi32(lo, hi);          /* reflectivities, low 8 bytes */
                }
                vdk_t16(d);
                const int64_t slot = 32 * b + k8;
                for (int k = 0; k < 8; ++k)
                    _mm_store_si128((__m128i *)&D[slot + k][g], d[k]);
                __m128i c[4], e[4];
                for (int i = 0; i < 4; ++i) c[i] = _mm_unpacklo_epi8(r[2 * i], r[2 * i + 1]);
                e[0] = _mm_unpacklo_epi16(c[0], c[1]);          /* points 0..3, packets 0..3 */
                e[1] = _mm_unpackhi_epi16(c[0], c[1]);          /* points 4..7, packets 0..3 */
                e[2] = _mm_unpacklo_epi16(c[2], c[3]);
                e[3] = _mm_unpackhi_epi16(c[2], c[3]);
                const __m128i pts[4] = {    /* points 0, 1 | 2, 3 | 4, 5 | 6, 7 of packets 0..7 */
                    _mm_unpacklo_epi32(e[0], e[2]), _mm_unpackhi_epi32(e[0], e[2]),
                    _mm_unpacklo_epi32(e[1], e[3]), _mm_unpackhi_epi32(e[1], e[3])};
                for (int i = 0; i < 4; ++i) {
                    _mm_storel_epi64((__m128i *)&I[slot + 2 * i][g], pts[i]);
                    _mm_storeh_pd((double *)&I[slot + 2 * i + 1][g], _mm_castsi128_pd(pts[i]));
                }
            }
        if (!angles) continue;
        float base[8][VDK_BLOCKS], gap[8][VDK_BLOCKS];
        for (int j = 0; j < 8; ++j)
            vdk_blocks(pkt[j], family, dual, n_blocks, base[j], gap[j]);
        const __m256 zero = _mm256_setzero_ps(), full = _mm256_set1_ps(36000.0f);
        const __m256 half = _mm256_set1_ps(0.5f), scale = _mm256_set1_ps((float)110.592);
        const __m256i mask = _mm256_set1_epi32(0xFFFF), turn = _mm256_set1_epi32(36000);
        const __m256i top = _mm256_set1_epi32(35999);
        __m256 Bs[VDK_BLOCKS], Gs[VDK_BLOCKS];
        for (int64_t b = 0; b < n_blocks; ++b) {
            const __m256 B = _mm256_setr_ps(base[0][b], base[1][b], base[2][b], base[3][b],
                                            base[4][b], base[5][b], base[6][b], base[7][b]);
            const __m256 G = _mm256_setr_ps(gap[0][b], gap[1][b], gap[2][b], gap[3][b],
                                            gap[4][b], gap[5][b], gap[6][b], gap[7][b]);
            Bs[b] = B, Gs[b] = G;
            if (twin[b] >= 0) {              /* same lasers, same base and gap: same angles */
                const __m256i same = _mm256_and_si256(
                    _mm256_cmpeq_epi32(_mm256_castps_si256(B), _mm256_castps_si256(Bs[twin[b]])),
                    _mm256_cmpeq_epi32(_mm256_castps_si256(G), _mm256_castps_si256(Gs[twin[b]])));
                if (_mm256_movemask_epi8(same) == -1) {
                    for (int k = 0; k < 32; ++k)
                        _mm_store_si128((__m128i *)&A[32 * b + k][g],
                                        _mm_load_si128((const __m128i *)&A[32 * twin[b] + k][g]));
                    continue;
                }
            }
            for (int k = 0; k < 32; ++k) {
                const int64_t slot = 32 * b + k;
                __m256 term = _mm256_mul_ps(G, _mm256_set1_ps(factor[slot]));
                if (family == 0) term = _mm256_div_ps(term, scale);
                const __m256 sum = _mm256_add_ps(B, term);
                const __m256d rot = _mm256_set1_pd(rotation[slot]);
                const __m128 lo = _mm256_cvtpd_ps(
                    _mm256_sub_pd(_mm256_cvtps_pd(_mm256_castps256_ps128(sum)), rot));
                const __m128 hi = _mm256_cvtpd_ps(
                    _mm256_sub_pd(_mm256_cvtps_pd(_mm256_extractf128_ps(sum, 1)), rot));
                __m256 value = _mm256_set_m128(hi, lo);
                value = _mm256_blendv_ps(value, _mm256_add_ps(value, full),
                                         _mm256_cmp_ps(value, zero, _CMP_LT_OQ));
                __m256i cw = _mm256_cvttps_epi32(_mm256_floor_ps(_mm256_add_ps(value, half)));
                cw = _mm256_and_si256(cw, mask);
                cw = _mm256_sub_epi32(cw, _mm256_and_si256(_mm256_cmpgt_epi32(cw, top), turn));
                const __m256i ccw = _mm256_andnot_si256(
                    _mm256_cmpeq_epi32(cw, _mm256_setzero_si256()), _mm256_sub_epi32(turn, cw));
                _mm_store_si128((__m128i *)&A[slot][g],
                                _mm_packus_epi32(_mm256_castsi256_si128(ccw),
                                                 _mm256_extracti128_si256(ccw, 1)));
            }
        }
    }
}

/*
 * vdk_fill for one firing sequence per packet (seqs == 1: column c = packet begin + c), whole
 * tiles of VDK_T columns: each tile gathered slot-major (vdk_tile), then each row h written
 * from its slot's rows (the row permutation in the copies) with 32-byte stores, the
 * identical-pair rule as a vector compare and blend. Returns the columns done (a multiple of
 * VDK_T), or 0 when a used slot has no angle (a block beyond n_blocks with angles wanted).
 */
VDK_AVX2 static int64_t vdk_fill_one(const uint8_t *const *pkts, int64_t begin, int64_t count,
                                     int64_t column, int64_t returns, int64_t rows,
                                     int64_t width, const int16_t *slots, const float *factor,
                                     const double *rotation, int64_t family, int64_t dual,
                                     int64_t n_blocks, uint16_t *r0, uint8_t *i0, uint16_t *r1,
                                     uint8_t *i1, uint16_t *a0, uint16_t *a1)
{
    _Alignas(64) uint16_t D[VDK_SLOTS][VDK_T];
    _Alignas(64) uint16_t A[VDK_SLOTS][VDK_T];
    _Alignas(64) uint8_t I[VDK_SLOTS][VDK_T];
    int64_t most = 0;
    for (int64_t i = 0; i < returns * rows; ++i) {
        if (slots[i] < 0 || slots[i] >= VDK_SLOTS) return 0;
        most = slots[i] > most ? slots[i] : most;
    }
    const int64_t nb = most / 32 + 1;
    if (a0 && nb > n_blocks) return 0;
    const int16_t *s0 = slots, *s1 = slots + rows;      /* (R, 1, H) */
    int64_t twin[VDK_BLOCKS];        /* an earlier block with the same lasers (factor, rotation) */
    for (int64_t b = 0; b < n_blocks; ++b) {
        twin[b] = -1;
        for (int64_t e = 0; e < b && twin[b] < 0; ++e)
            if (!memcmp(factor + 32 * b, factor + 32 * e, 32 * sizeof *factor) &&
                !memcmp(rotation + 32 * b, rotation + 32 * e, 32 * sizeof *rotation))
                twin[b] = e;
    }
    int64_t c0 = 0;
    for (; c0 + VDK_T <= count; c0 += VDK_T) {
        vdk_tile(pkts + begin + c0, nb, a0 != NULL, family, dual, n_blocks,
                 factor, rotation, twin, D, I, A);
        const int64_t col = column + c0;
        for (int64_t h = 0; h < rows; ++h) {
            const int64_t at = h * width + col;
            const int64_t x = s0[h], y = returns == 2 ? s1[h] : 0;
            if (col + VDK_T + VDK_PF <= width) {          /* the lines of the tiles ahead */
                __builtin_prefetch(r0 + at + VDK_PF, 1);
                __builtin_prefetch(i0 + at + VDK_PF, 1);
                if (returns == 2) {
                    __builtin_prefetch(r1 + at + VDK_PF, 1);
                    __builtin_prefetch(i1 + at + VDK_PF, 1);
                }
                if (a0) {
                    __builtin_prefetch(a0 + at + VDK_PF, 1);
                    if (returns == 2) __builtin_prefetch(a1 + at + VDK_PF, 1);
                }
            }
            for (int c = 0; c < VDK_T; c += 16) {
                const __m256i d0 = _mm256_load_si256((const __m256i *)&D[x][c]);
                _mm256_storeu_si256((__m256i *)(r0 + at + c), d0);
                _mm_storeu_si128((__m128i *)(i0 + at + c),
                                 _mm_load_si128((const __m128i *)&I[x][c]));
                __m256i eq = _mm256_setzero_si256();
                if (returns == 2) {
                    const __m256i d1 = _mm256_load_si256((const __m256i *)&D[y][c]);
                    _mm256_storeu_si256((__m256i *)(r1 + at + c), d1);
                    _mm_storeu_si128((__m128i *)(i1 + at + c),
                                     _mm_load_si128((const __m128i *)&I[y][c]));
                    eq = _mm256_cmpeq_epi16(d0, d1);
                }
                if (a0) {
                    __m256i first = _mm256_load_si256((const __m256i *)&A[x][c]);
                    if (returns == 2) {
                        const __m256i last = _mm256_load_si256((const __m256i *)&A[y][c]);
                        _mm256_storeu_si256((__m256i *)(a1 + at + c), last);
                        /* an identical pair: the last return's angle */
                        first = _mm256_blendv_epi8(first, last, eq);
                    }
                    _mm256_storeu_si256((__m256i *)(a0 + at + c), first);
                }
            }
        }
    }
    return c0;
}

/* Whether this CPU runs vdk_fill_one (AVX2); asked once (0 / 1, -1 before the first call). */
static int vdk_has_avx2 = -1;

static int vdk_avx2(void)
{
    if (vdk_has_avx2 < 0) {
        __builtin_cpu_init();
        vdk_has_avx2 = __builtin_cpu_supports("avx2") ? 1 : 0;
    }
    return vdk_has_avx2;
}
#endif /* VDK_SIMD */

/*
 * Decode `count` firing sequences, from sequence `begin` of the packets given by address
 * (pkts[p]: the 1206 bytes of packet p; sequence q = sequence q % S of packet q / S), into
 * columns column .. column + count - 1 of the (H, width) channel views r0 / i0 (uint16 range,
 * uint8 intensity of return slot 0, the strongest or only), r1 / i1 (slot 1, the last return; unused when returns == 1) and, unless
 * a0 is NULL, the uint16 angle views a0 / a1 (a1 unused when returns == 1).
 *
 * offsets: (R, S, H) byte offset in a packet of the distance (reflectivity at + 2) of return
 * slot r, sequence s, row h; slots: (R, S, H) its point slot 32 * block + k; factor (384) float32
 * firing factor and rotation (384) float64 rot_correction (0.01 deg) of each slot's laser;
 * family 0 VLP-16, 1 VLP-32C / HDL-32E, 2 VLS-128; n_blocks: the blocks Nebula walks; simd: 0
 * forces the portable path.
 *
 * One sequence per packet (a dual-return VLS-128) on an AVX2 CPU, unless simd is 0: whole tiles
 * of VDK_T columns by vdk_fill_one, the rest by vdk_fill_tiles; every other layout by
 * vdk_fill_tiles. Both give the same bytes. Returns 0, -1 for an unsupported shape (more than
 * VDK_ROWS rows, returns not 1 or 2), -2 when the tile buffers cannot be allocated.
 */
VDK_EXPORT int64_t vdk_fill(const uint8_t *const *pkts, int64_t begin, int64_t count,
                            int64_t column, int64_t returns, int64_t seqs, int64_t rows,
                            int64_t width,
                            const int32_t *offsets, const int16_t *slots, const float *factor,
                            const double *rotation, int64_t family, int64_t dual,
                            int64_t n_blocks, uint16_t *r0, uint8_t *i0, uint16_t *r1,
                            uint8_t *i1, uint16_t *a0, uint16_t *a1, int64_t simd)
{
    if (rows > VDK_ROWS || returns < 1 || returns > 2) return -1;
    if (count <= 0) return 0;
    int64_t done = 0;
#ifdef VDK_SIMD
    if (simd && seqs == 1 && count >= VDK_T && vdk_avx2())
        done = vdk_fill_one(pkts, begin, count, column, returns, rows, width, slots, factor,
                            rotation, family, dual, n_blocks, r0, i0, r1, i1, a0, a1);
#else
    (void)simd;
#endif
    if (done == count) return 0;
    return vdk_fill_tiles(pkts, begin + done, count - done, column + done, returns, seqs, rows,
                          width, offsets, slots, factor, rotation, family, dual, n_blocks, r0,
                          i0, r1, i1, a0, a1);
}

/* ------------------------------------------------------------------------- Python module */

/*
 * table(pairs, addresses, stamps) -> int: for a list of (stamp_ns, payload) pairs, the address
 * of each payload's bytes into `addresses` (writable buffer of n uintptr) and its stamp into
 * `stamps` (writable buffer of n int64), in one pass; returns the index of the first pair that
 * is not a 2-tuple of an int (within int64) and a 1206-byte `bytes` (then the caller takes the
 * general path), or n. The payloads are read later through the addresses: the caller keeps
 * `pairs` alive (bytes are immutable, so the addresses stay valid and the bytes unchanged).
 */
static PyObject *vdk_table(PyObject *self, PyObject *args)
{
    PyObject *pairs;
    Py_buffer addr, stamp;
    (void)self;
    if (!PyArg_ParseTuple(args, "O!w*w*", &PyList_Type, &pairs, &addr, &stamp)) return NULL;
    const Py_ssize_t n = PyList_GET_SIZE(pairs);
    Py_ssize_t p = 0;
    if (addr.len < n * (Py_ssize_t)sizeof(uintptr_t) ||
        stamp.len < n * (Py_ssize_t)sizeof(int64_t)) {
        PyBuffer_Release(&addr);
        PyBuffer_Release(&stamp);
        PyErr_SetString(PyExc_ValueError, "table: the output buffers are too small");
        return NULL;
    }
    uintptr_t *out = (uintptr_t *)addr.buf;
    int64_t *times = (int64_t *)stamp.buf;
    for (; p < n; ++p) {
        PyObject *pair = PyList_GET_ITEM(pairs, p);
        if (!PyTuple_CheckExact(pair) || PyTuple_GET_SIZE(pair) != 2) break;
        PyObject *t = PyTuple_GET_ITEM(pair, 0), *data = PyTuple_GET_ITEM(pair, 1);
        if (!PyBytes_CheckExact(data) || PyBytes_GET_SIZE(data) != VDK_PACKET ||
            !PyLong_CheckExact(t))
            break;
        int overflow = 0;
        const long long value = PyLong_AsLongLongAndOverflow(t, &overflow);
        if (overflow || (value == -1 && PyErr_Occurred())) {
            PyErr_Clear();
            break;
        }
        times[p] = (int64_t)value;
        out[p] = (uintptr_t)PyBytes_AS_STRING(data);
    }
    PyBuffer_Release(&addr);
    PyBuffer_Release(&stamp);
    return PyLong_FromSsize_t(p);
}

static PyMethodDef vdk_methods[] = {
    {"table", vdk_table, METH_VARARGS,
     "table(pairs, addresses, stamps) -> index of the first odd pair, or len(pairs)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef vdk_module = {
    PyModuleDef_HEAD_INIT, "_velokernel",
    "Compiled Velodyne packet kernel (loaded with ctypes by converters._kernels.velodyne; "
    "table() is its one Python function).",
    -1, vdk_methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__velokernel(void)
{
    PyObject *module = PyModule_Create(&vdk_module);
    if (module && PyModule_AddIntConstant(module, "ABI", VDK_ABI) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
