// Numerics shared by the compute shaders, written to match the CPU backend's f64 helpers
// as closely as f32 allows.

const float PI = 3.14159265358979;
const float BIG = 3.0e38;

// e^x − 1 without the cancellation of exp(x) − 1 near zero (Kahan's trick).
float expm1_accurate(float x) {
    float u = exp(x);
    if (u == 1.0) {
        return x;
    }
    float um1 = u - 1.0;
    if (um1 == -1.0) {
        return -1.0;
    }
    return um1 * x / log(u);
}

// ∫₀ᵈ e^(−k·u) du, also for k near zero or negative.
float integral_exp(float k, float d) {
    float kd = k * d;
    if (abs(kd) < 1e-4) {
        return d * (1.0 - 0.5 * kd + kd * kd / 6.0);
    }
    return -expm1_accurate(-kd) / k;
}

// ∫ e^(−σ·(ℓ(t) + t − a)) dt over [p, q], ℓ linear there from `depth_p` to `depth_q` with
// slope `slope`: the exponent taken at the lighter end, as the CPU's stretch_integral, so
// that e^(−σ·…) and the integral never meet as 0 · ∞ on a steep line.
float stretch_integral(float sigma, float a, float p, float q, float depth_p, float depth_q,
                       float slope) {
    float k = sigma * (1.0 + slope);
    if (k >= 0.0) {
        return exp(-sigma * (depth_p + p - a)) * integral_exp(k, q - p);
    }
    return exp(-sigma * (depth_q + q - a)) * integral_exp(-k, q - p);
}

// Clamp to [0, 1] with NaN read as 0, like the CPU's `unit`.
float unit(float v) {
    return isnan(v) ? 0.0 : clamp(v, 0.0, 1.0);
}

float finite_or_zero(float v) {
    return (isnan(v) || isinf(v)) ? 0.0 : v;
}

// The smallest and largest K over a rectified sample's interval from K at its centre and
// its index's (near, far) factors; `reciprocal` where K scales with 1/s
// (EpipolarMap::sample_bounds).
vec2 sample_bounds_from(vec2 factors, float centre, bool reciprocal) {
    if (!reciprocal) {
        return vec2(centre - factors.x, centre + factors.x);
    }
    if (centre == 0.0 || isinf(centre)) {
        return vec2(centre);
    }
    return centre > 0.0 ? vec2(centre * factors.y, centre * factors.x)
                        : vec2(centre * factors.x, centre * factors.y);
}
