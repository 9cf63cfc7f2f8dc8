// Prototype (measurement only, not shipped): softplus(x) = max(x,0) + log1p(exp(-|x|)) in AVX2 + FMA.
#include <immintrin.h>
#include <stddef.h>
#include <math.h>

static inline __m256 exp_neg(__m256 x) {            // exp(x) for x <= 0 (Cephes-style: 2^n * p(r))
    const __m256 log2e = _mm256_set1_ps(1.44269504088896341f);
    const __m256 ln2hi = _mm256_set1_ps(0.693359375f), ln2lo = _mm256_set1_ps(-2.12194440e-4f);
    x = _mm256_max_ps(x, _mm256_set1_ps(-87.0f));
    __m256 n = _mm256_round_ps(_mm256_mul_ps(x, log2e), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    __m256 r = _mm256_fnmadd_ps(n, ln2hi, x);
    r = _mm256_fnmadd_ps(n, ln2lo, r);
    __m256 p = _mm256_set1_ps(1.9875691500E-4f);
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.3981999507E-3f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(8.3334519073E-3f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(4.1665795894E-2f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(1.6666665459E-1f));
    p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(5.0000001201E-1f));
    __m256 r2 = _mm256_mul_ps(r, r);
    p = _mm256_fmadd_ps(p, r2, _mm256_add_ps(r, _mm256_set1_ps(1.0f)));
    __m256i e = _mm256_slli_epi32(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)), 23);
    return _mm256_mul_ps(p, _mm256_castsi256_ps(e));
}

static inline __m256 log_1_2(__m256 y) {            // log(y) for y in [1, 2] (Cephes logf polynomial)
    __m256i yi = _mm256_castps_si256(y);
    __m256 e = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(yi, 23), _mm256_set1_epi32(127)));
    __m256 m = _mm256_castsi256_ps(_mm256_or_si256(_mm256_and_si256(yi, _mm256_set1_epi32(0x007fffff)),
                                                    _mm256_set1_epi32(0x3f800000)));      // [1, 2)
    __m256 big = _mm256_cmp_ps(m, _mm256_set1_ps(1.41421356f), _CMP_GT_OQ);              // m > sqrt2: m/2, e+1
    m = _mm256_blendv_ps(m, _mm256_mul_ps(m, _mm256_set1_ps(0.5f)), big);
    e = _mm256_add_ps(e, _mm256_and_ps(big, _mm256_set1_ps(1.0f)));
    __m256 x = _mm256_sub_ps(m, _mm256_set1_ps(1.0f));
    __m256 p = _mm256_set1_ps(7.0376836292E-2f);
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(-1.1514610310E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(1.1676998740E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(-1.2420140846E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(1.4249322787E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(-1.6668057665E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(2.0000714765E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(-2.4999993993E-1f));
    p = _mm256_fmadd_ps(p, x, _mm256_set1_ps(3.3333331174E-1f));
    __m256 x2 = _mm256_mul_ps(x, x);
    p = _mm256_mul_ps(_mm256_mul_ps(p, x), x2);
    p = _mm256_fmadd_ps(e, _mm256_set1_ps(-2.12194440e-4f), p);
    p = _mm256_fnmadd_ps(x2, _mm256_set1_ps(0.5f), p);
    x = _mm256_add_ps(x, p);
    return _mm256_fmadd_ps(e, _mm256_set1_ps(0.693359375f), x);
}

void softplus_avx2_1(const float *in, float *out, size_t n) {
    const __m256 sign = _mm256_set1_ps(-0.0f), one = _mm256_set1_ps(1.0f), zero = _mm256_setzero_ps();
    size_t i = 0;
    for (; i + 8 <= n; i += 8) {
        __m256 x = _mm256_loadu_ps(in + i);
        __m256 t = exp_neg(_mm256_or_ps(x, sign));                  // exp(-|x|)
        __m256 y = _mm256_add_ps(_mm256_max_ps(x, zero), log_1_2(_mm256_add_ps(t, one)));
        _mm256_storeu_ps(out + i, y);
    }
    for (; i < n; i++) { float x = in[i]; out[i] = fmaxf(x, 0.f) + log1pf(expf(-fabsf(x))); }
}

void softplus_avx2(const float *in, float *out, size_t n) {     // 2 threads (OpenMP), blocks of 64k floats
    const size_t B = 65536;
    #pragma omp parallel for schedule(static)
    for (size_t b = 0; b < n; b += B) softplus_avx2_1(in + b, out + b, (n - b < B) ? n - b : B);
}
