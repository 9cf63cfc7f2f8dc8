// Prototype (measurement only, not shipped): channels-last bilinear sampling fused with the attention
// weighting, zero padding, align_corners=False.  canvas (Hc, Wc, C) with C = heads * dh;
// gx, gy, w: (heads, P, Q) grid_sample coordinates in [-1, 1] and attention weights; out (heads, dh, Q).
#include <immintrin.h>
#include <math.h>
#include <string.h>

void deform_sample(const float *canvas, int Hc, int Wc, int C, int heads, int P, int Q,
                   const float *gx, const float *gy, const float *w, float *out) {
    const int dh = C / heads;   // 16 here: two AVX registers
    #pragma omp parallel for collapse(2) schedule(static)
    for (int h = 0; h < heads; h++) {
        for (int q = 0; q < Q; q++) {
            __m256 a0 = _mm256_setzero_ps(), a1 = _mm256_setzero_ps();
            for (int p = 0; p < P; p++) {
                size_t i = ((size_t)h * P + p) * Q + q;
                float wt = w[i];
                if (wt == 0.f) continue;
                float x = ((gx[i] + 1.f) * Wc - 1.f) * 0.5f, y = ((gy[i] + 1.f) * Hc - 1.f) * 0.5f;
                float fx = floorf(x), fy = floorf(y);
                int x0 = (int)fx, y0 = (int)fy;
                float dx = x - fx, dy = y - fy;
                float cw[4] = {(1 - dx) * (1 - dy), dx * (1 - dy), (1 - dx) * dy, dx * dy};
                int xs[4] = {x0, x0 + 1, x0, x0 + 1}, ys[4] = {y0, y0, y0 + 1, y0 + 1};
                for (int c = 0; c < 4; c++) {
                    if (xs[c] < 0 || xs[c] >= Wc || ys[c] < 0 || ys[c] >= Hc) continue;
                    const float *v = canvas + ((size_t)ys[c] * Wc + xs[c]) * C + h * dh;
                    __m256 s = _mm256_set1_ps(wt * cw[c]);
                    a0 = _mm256_fmadd_ps(s, _mm256_loadu_ps(v), a0);
                    a1 = _mm256_fmadd_ps(s, _mm256_loadu_ps(v + 8), a1);
                }
            }
            float tmp[16];
            _mm256_storeu_ps(tmp, a0); _mm256_storeu_ps(tmp + 8, a1);
            for (int d = 0; d < dh; d++) out[((size_t)h * dh + d) * Q + q] = tmp[d];
        }
    }
}
