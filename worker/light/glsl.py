"""GLSL 330 of the physical model: surface radiance under the water column (`SURFACE`) and the water along view
rays (`VOLUME`, the twin of `seasynth.worker.light.volume`). Terms are compiled in or out by defines: WITH_SUN,
WITH_SUN_SHADOW, WITH_SKY, WITH_SCATTER, WITH_SOLVED, LAMPS (a count), so a term a frame does not need costs
nothing."""

from seasynth.worker.light import caustics
from seasynth.worker.light.lamps import (
                                BACKSCATTER_NODES,
                                CUTOFF_OPTICAL_DEPTH,
                                LAMP_Z_SPREAD,
                                MIN_LAMP_DISTANCE_M,
                                REACH_MARGIN_RAD,
)
from seasynth.worker.light.sky import SKY_PHASE_NODES
from seasynth.worker.light.solved import ED_NODES, LAMP_SEEN_CAP, VIEW_TABLE_GLSL
from seasynth.worker.light.volume import MU_SKY
from seasynth.worker.render import materials
from seasynth.worker.render.shaders import SURFACE_BEGIN

MAX_LAMPS = 4
SOFT_SHADOW_RADIUS_M = 0.05  # the forward-scattered sun arrives within a few degrees: its shadows blur by this
# Shadow lookups start off the surface along its normal (normal-offset shadows), by this many map texels plus this
# many camera pixels' footprints: a sample is shaded on its triangle's plane, which may lie up to a pixel beyond the
# triangle (pixel-centre interpolation of a partly covered pixel; per-sample shading on llvmpipe), and there it can
# sit under the neighbouring triangle that the map holds: it must not shadow itself.
NORMAL_OFFSET_TEXELS = 1.5
NORMAL_OFFSET_PIXELS = 0.5

UNIFORMS = (
    "u_world_z", "u_surface_z", "u_c", "u_K", "u_b", "u_g", "u_sun_cam", "u_sun_world", "u_mu_w", "u_E0", "u_Esky",
    "u_sun_shadow", "u_sun_soft", "u_sun_from_cam", "u_sun_texel_m", "u_sun_soft_texel_m", "u_pixel_angle", "u_cam_depth",
    "u_world_from_cam", "u_K_inv", "u_sky_phase", "u_world_x", "u_world_y", "u_sun_azimuth", "u_ed_sun",
    "u_ed_sky", "u_ed_step", *caustics.UNIFORMS,
    *(f"u_lamp_{what}[{i}]" for what in ("pos", "dir", "I", "cone", "energy", "from_cam", "shadow", "texel")
      for i in range(MAX_LAMPS)),
)

_COMMON = f"""
const float PI = 3.14159265358979;
const float X_MAX = 87.0;
const float MU_SKY = {MU_SKY!r};
const int ED_NODES = {ED_NODES};
const float LAMP_SEEN_CAP = {LAMP_SEEN_CAP!r};
const float NORMAL_OFFSET_TEXELS = {NORMAL_OFFSET_TEXELS!r};
const float NORMAL_OFFSET_PIXELS = {NORMAL_OFFSET_PIXELS!r};
const float SNELL_COS = 0.66131187;       // cos(48.6 deg)
const float SNELL_SIN2 = 0.56266999;      // sin(48.6 deg)^2
float exp_neg(float x) {{ return x >= X_MAX ? 0.0 : exp(-x); }}
vec3 exp_neg3(vec3 x) {{ return vec3(exp_neg(x.x), exp_neg(x.y), exp_neg(x.z)); }}
// lamps.light_factor: the unscattered beam with the sharp profile, the forward-scattered rest spread in angle
// (LAMP_SPREAD) or, without it, kept in the sharp profile.
#ifdef LAMP_SPREAD
vec3 edge_energy(vec3 lo, vec3 hi) {{   // 2 sin^2(m/2) + cos(m) (1 - sinc(x)), x <= pi/2: a series to x^10 (< 4e-8)
    vec3 x2 = 0.25 * (hi - lo) * (hi - lo);
    vec3 one_minus_sinc = x2 * (1.0 / 6.0 - x2 * (1.0 / 120.0 - x2 * (1.0 / 5040.0 - x2 * (1.0 / 362880.0
                          - x2 * (1.0 / 39916800.0)))));
    vec3 s = sin(0.25 * (lo + hi));
    vec3 s2 = 2.0 * s * s;
    return s2 + (1.0 - s2) * one_minus_sinc;
}}
#endif
// x0: optical depth the light crosses beyond the lamp's leg (the camera's, K t, in the water along a ray)
vec3 lamp_light(float cos_axis, float d, vec3 x0, vec2 cone, float energy,   // cone: (beam, cutoff) half angles
                vec3 c, vec3 K, vec3 b, float g) {{
    float ang = acos(clamp(cos_axis, -1.0, 1.0));
    float sharp = clamp((cone.y - ang) / max(cone.y - cone.x, 1e-9), 0.0, 1.0);
#ifdef LAMP_SPREAD
    vec3 direct = exp_neg3(c * d + x0);
    vec3 bd = b * d;
    vec3 n = mix(bd / max(1.0 - exp(-bd), vec3(1e-30)), vec3(1.0), lessThan(bd, vec3(1e-4)));
    float w = cone.y - cone.x, m = 0.5 * (cone.x + cone.y);
    vec3 w2 = sqrt(w * w + 4.0 * (1.0 - g) * n);
    vec3 lo = max(m - 0.5 * w2, 0.0), hi = min(m + 0.5 * w2, PI);
    vec3 spread = energy / edge_energy(lo, hi) * clamp((hi - ang) / max(hi - lo, vec3(1e-9)), 0.0, 1.0);
    return direct * sharp + (exp_neg3(K * d + x0) - direct) * spread;
#else
    return exp_neg3(K * d + x0) * sharp;
#endif
}}
"""

SURFACE = (
    """
#version 330 core
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
uniform vec3 u_scale;
uniform vec3 u_bias;
uniform vec4 u_world_z;        // row z of world_from_cam: world z of a camera-frame point
uniform float u_surface_z;
uniform vec3 u_c;
uniform vec3 u_K;
uniform vec3 u_b;
uniform float u_g;
uniform vec3 u_sun_cam;        // towards the sun, refracted, camera frame
uniform float u_mu_w;          // its cosine to the vertical
uniform vec3 u_E0;
uniform vec3 u_Esky;
uniform sampler2DShadow u_sun_shadow;
uniform sampler2DShadow u_sun_soft;   // the same view of the sun at a texel of about SOFT_SHADOW_RADIUS_M
uniform mat4 u_sun_from_cam;   // shadow-map texture coordinates (xy) and depth (z) from the camera frame (both maps)
uniform float u_sun_texel_m;   // metres per sun-map texel
uniform float u_sun_soft_texel_m;
uniform float u_pixel_angle;   // a camera pixel's width in metres per metre of range
#if LAMPS > 0
uniform vec3 u_lamp_pos[LAMPS];
uniform vec3 u_lamp_dir[LAMPS];
uniform vec3 u_lamp_I[LAMPS];
uniform vec2 u_lamp_cone[LAMPS];
uniform float u_lamp_energy[LAMPS];   // lamps.cone_energy: the profile's solid angle over 2 pi
uniform mat4 u_lamp_from_cam[LAMPS];
uniform sampler2DShadow u_lamp_shadow[LAMPS];
uniform float u_lamp_texel[LAMPS];   // metres per lamp-map texel per metre from the lamp
#endif
layout(location = 0) out vec4 o_J;
"""
    + materials.FRAGMENT
    + _COMMON
    + """
#ifdef WITH_SOLVED
uniform vec3 u_ed_sun[ED_NODES];   // solved.DepthTable: log E_d per node, the sun's diffuse part and the sky's
uniform vec3 u_ed_sky[ED_NODES];
uniform float u_ed_step;
// seen through c, the lamps' light on a surface keeps its forward-scattered part through K (solved.LAMP_SEEN_CAP)
#define LAMP_SEEN(r) exp(min((u_c - u_K) * (r), vec3(LAMP_SEEN_CAP)))
#else
#define LAMP_SEEN(r) vec3(1.0)
#endif
#ifdef WITH_CAUSTICS
uniform vec4 u_world_x;        // rows x and y of world_from_cam
uniform vec4 u_world_y;
"""
    + caustics.GLSL
    + """
#endif
float shadow_tap(sampler2DShadow map, vec3 p) {
    return (any(lessThan(p.xy, vec2(0.0))) || any(greaterThan(p.xy, vec2(1.0))) || p.z >= 1.0)
        ? 1.0 : texture(map, p);
}
#if LAMPS > 0
// A lamp's map covers its cone and a margin (shadows.lamp_clip_from_cam); light spread past it by scattering
// (lamps.light_factor) is left out there rather than left unshadowed: a lamp inside an object lights nothing.
float lamp_tap(sampler2DShadow map, vec3 p) {
    return (any(lessThan(p.xy, vec2(0.0))) || any(greaterThan(p.xy, vec2(1.0)))) ? 0.0
        : (p.z >= 1.0 ? 1.0 : texture(map, p));
}
// Sampler arrays take constant indices only (GLSL 1.30 and later).
float lamp_visibility(int l, vec3 p) {
    if (l == 0) return lamp_tap(u_lamp_shadow[0], p);
#if LAMPS > 1
    if (l == 1) return lamp_tap(u_lamp_shadow[1], p);
#endif
#if LAMPS > 2
    if (l == 2) return lamp_tap(u_lamp_shadow[2], p);
#endif
#if LAMPS > 3
    if (l == 3) return lamp_tap(u_lamp_shadow[3], p);
#endif
    return 0.0;
}
#endif
void main() {
"""
    + SURFACE_BEGIN
    + """
    float depth = max(u_surface_z - (dot(u_world_z.xyz, v_pos) + u_world_z.w), 0.0);
    vec3 E = vec3(0.0);
    float pixel_m = NORMAL_OFFSET_PIXELS * u_pixel_angle * length(v_pos);
#ifdef WITH_SOLVED
    // solved.irradiance: the solved column's E_d, log-linear between its depth nodes
    float xe = depth / u_ed_step;
    int ie = clamp(int(floor(xe)), 0, ED_NODES - 2);
    float fe = xe - float(ie);
#endif
#ifdef WITH_SUN
    float cos_i = max(dot(n, u_sun_cam), 0.0);
#if defined(WITH_SUN_SHADOW) || defined(WITH_CAUSTICS) || defined(WITH_SOLVED)
    vec3 direct = exp_neg3(u_c * (depth / u_mu_w));   // the unscattered beam's share
#endif
#ifdef WITH_SOLVED
    vec3 total = direct + exp(mix(u_ed_sun[ie], u_ed_sun[ie + 1], fe));
#else
    vec3 total = exp_neg3(u_K * (depth / u_mu_w));
#endif
#ifdef WITH_CAUSTICS
    float focus = caustic_factor(vec3(dot(u_world_x.xyz, v_pos) + u_world_x.w, dot(u_world_y.xyz, v_pos) + u_world_y.w,
                                      0.0), depth);
#else
    float focus = 1.0;
#endif
#ifdef WITH_SUN_SHADOW
    // the unscattered beam's share is shadowed sharply, the forward-scattered rest softly
    vec4 q = u_sun_from_cam * vec4(v_pos + n * (NORMAL_OFFSET_TEXELS * u_sun_texel_m + pixel_m), 1.0);
    float v_hard = shadow_tap(u_sun_shadow, q.xyz);
    // one filtered tap of the coarse map: its 2x2 texels' comparisons blend over about a texel's radius
    vec4 qs = u_sun_from_cam * vec4(v_pos + n * (NORMAL_OFFSET_TEXELS * u_sun_soft_texel_m + pixel_m), 1.0);
    float v_soft = shadow_tap(u_sun_soft, qs.xyz);
    E += u_E0 * cos_i * (direct * (v_hard * focus) + (total - direct) * v_soft);
#elif defined(WITH_CAUSTICS)
    E += u_E0 * cos_i * (total + direct * (focus - 1.0));
#else
    E += u_E0 * cos_i * total;
#endif
#endif
#ifdef WITH_SKY
    float up = dot(u_world_z.xyz, n);   // world z of the normal
#ifdef WITH_SOLVED
    E += u_Esky * exp(mix(u_ed_sky[ie], u_ed_sky[ie + 1], fe)) * ((0.5 + 0.5 * up) * occlusion);
#else
    E += u_Esky * exp_neg3(u_K * (depth / MU_SKY)) * ((0.5 + 0.5 * up) * occlusion);
#endif
#endif
#if LAMPS > 0
    vec3 seen = LAMP_SEEN(length(v_pos));
    for (int l = 0; l < LAMPS; ++l) {
        vec3 to_p = v_pos - u_lamp_pos[l];
        float d = max(length(to_p), 1e-3);
        vec3 wi = to_p / d;
        float cos_n = max(dot(n, -wi), 0.0);
        if (cos_n <= 0.0) continue;
        vec3 lit = lamp_light(dot(wi, u_lamp_dir[l]), d, vec3(0.0), u_lamp_cone[l], u_lamp_energy[l], u_c, u_K, u_b,
                              u_g);
        vec4 q = u_lamp_from_cam[l] * vec4(v_pos + n * (NORMAL_OFFSET_TEXELS * u_lamp_texel[l] * d + pixel_m), 1.0);
        float vis = q.w > 0.0 ? lamp_visibility(l, q.xyz / q.w) : 0.0;
        E += u_lamp_I[l] * (cos_n * vis / (d * d)) * lit * seen;
    }
#endif
    o_J = vec4(albedo * E, 1.0);
}
"""
)

# The resolve shader's water for the physical model: defines `void water_pixel(vec3 w_world)`, called once per pixel
# with its centre's ray, then `vec3 water(vec3 J, float z, vec3 w_world, vec3 w_cam)` per sample (z = +inf where no
# surface).
VOLUME = (
    _COMMON
    + f"""
uniform vec3 u_c;
uniform vec3 u_K;
uniform vec3 u_b;
uniform float u_g;
uniform vec3 u_sun_world;
uniform float u_mu_w;
uniform vec3 u_E0;
uniform vec3 u_Esky;
uniform float u_cam_depth;
uniform float u_sky_phase[{SKY_PHASE_NODES}];   // sky.sky_phase_table
#ifdef WITH_SOLVED
#define VIEW_C u_c   // the path radiance's view leg: the beam's c, J_ms carrying the scattered rest
#else
#define VIEW_C u_K
#endif
#if defined(WITH_SOLVED) && defined(WITH_SCATTER) && (defined(WITH_SUN) || defined(WITH_SKY))
#define WITH_JMS
{VIEW_TABLE_GLSL}
#endif
#if LAMPS > 0
uniform vec3 u_lamp_pos[LAMPS];
uniform vec3 u_lamp_dir[LAMPS];
uniform vec3 u_lamp_I[LAMPS];
uniform vec2 u_lamp_cone[LAMPS];
uniform float u_lamp_energy[LAMPS];   // lamps.cone_energy: the profile's solid angle over 2 pi
#endif
float hg(float mu, float g) {{
    float d = max(1.0 + g * g - 2.0 * g * mu, 1e-12);
    return (1.0 - g * g) / (4.0 * PI * d * sqrt(d));
}}
// integral_0^z exp(-x1 - alpha t) dt given e1 = exp(-x1), x1 >= 0 and x1 + alpha z >= 0; z = +inf needs alpha > 0.
float segment(float e1, float x1, float alpha, float z) {{
    if (isinf(z)) return alpha > 0.0 ? e1 / alpha : 0.0;
    float y = alpha * z;
    if (abs(y) < 1e-2) return z * e1 * (1.0 - y * (0.5 - y * (1.0 / 6.0 - y * (1.0 / 24.0))));
    return (e1 - exp_neg(x1 + y)) / alpha;
}}
// A term scattered into the ray: amp * integral_0^z exp(-x1 - alpha t) dt per channel; all but z are the pixel's.
struct Inscatter {{ vec3 amp; vec3 x1; vec3 e1; vec3 alpha; }};
Inscatter inscatter(vec3 amp, float path_cos, float wz) {{
    vec3 x1 = VIEW_C / path_cos * u_cam_depth;
    return Inscatter(amp, x1, exp_neg3(x1), VIEW_C - VIEW_C / path_cos * wz);
}}
vec3 inscattered(Inscatter s, float z) {{
    return s.amp * vec3(segment(s.e1.x, s.x1.x, s.alpha.x, z), segment(s.e1.y, s.x1.y, s.alpha.y, z),
                        segment(s.e1.z, s.x1.z, s.alpha.z, z));
}}
// What water() needs of the pixel's view ray (every sample of a pixel looks along the pixel centre's ray).
float g_to_surface;
#if defined(WITH_SCATTER) && defined(WITH_SUN)
Inscatter g_sun;
#endif
#if defined(WITH_SCATTER) && defined(WITH_SKY)
Inscatter g_sky;
#endif
#ifdef WITH_JMS
Inscatter g_ms;
#endif
void water_pixel(vec3 w) {{
    g_to_surface = w.z > 0.0 ? u_cam_depth / w.z : uintBitsToFloat(0x7F800000u);
#ifdef WITH_JMS
    vec3 jms, kj;
    view_table(w, jms, kj);
    g_ms = Inscatter(jms, vec3(0.0), vec3(1.0), u_c - kj * w.z);
#endif
#if defined(WITH_SCATTER) && defined(WITH_SUN)
    // the beam and its forward-scattered light scatter into the ray alike (one segment, the beam's phase function)
    g_sun = inscatter(u_b * (PI * u_E0) * hg(dot(w, u_sun_world), u_g), u_mu_w, w.z);
#endif
#if defined(WITH_SCATTER) && defined(WITH_SKY)
    float xs = (w.z + 1.0) * {0.5 * (SKY_PHASE_NODES - 1)!r};
    int js = clamp(int(floor(xs)), 0, {SKY_PHASE_NODES - 2});
    float p_sky = mix(u_sky_phase[js], u_sky_phase[js + 1], xs - float(js));
    g_sky = inscatter(u_b * (u_Esky / SNELL_SIN2 * p_sky), MU_SKY, w.z);
#endif
}}
#if defined(WITH_SCATTER) && LAMPS > 0
float lamp_reach(vec2 cone, float d_max) {{   // lamps.reach
    float r = cone.y;
#ifdef LAMP_SPREAD
    if (any(lessThan(u_K, u_c))) {{
        float bd = max(u_b.x, max(u_b.y, u_b.z)) * d_max;
        float n = bd < 1e-4 ? 1.0 : bd / max(1.0 - exp(-bd), 1e-30);
        float w = cone.y - cone.x;
        r = clamp(0.5 * (cone.x + cone.y) + 0.5 * sqrt(w * w + 4.0 * (1.0 - u_g) * n), cone.y, PI);
    }}
#endif
    return r + {REACH_MARGIN_RAD!r};
}}
vec2 cone_interval(vec3 w, vec3 apex, vec3 axis, float half_angle, float t_end) {{   // lamps.cone_interval
    if (half_angle >= 0.5 * PI) return vec2(0.0, t_end);
    vec3 q = -apex;
    float k = cos(half_angle);
    float A = dot(w, axis), B = dot(q, axis), C = dot(w, q), D = dot(q, q);
    float a2 = A * A - k * k, b2 = A * B - k * k * C, c2 = B * B - k * k * D;
    float sq = sqrt(max(b2 * b2 - a2 * c2, 0.0));
    float qq = -(b2 + (b2 < 0.0 ? -sq : sq));
    float r1 = clamp(qq / (abs(a2) < 1e-30 ? 1e-30 : a2), 0.0, t_end);
    float r2 = clamp(c2 / (abs(qq) < 1e-30 ? 1e-30 : qq), 0.0, t_end);
    float cuts[4] = float[4](0.0, min(r1, r2), max(r1, r2), t_end);
    float t0 = 1e30, t1 = -1e30;
    for (int i = 0; i < 3; ++i) {{
        float mid = 0.5 * (cuts[i] + cuts[i + 1]);
        if (mid * A + B >= k * length(w * mid + q)) {{ t0 = min(t0, cuts[i]); t1 = max(t1, cuts[i + 1]); }}
    }}
    return t0 > t1 ? vec2(0.0) : vec2(t0, t1);
}}
#endif
vec3 water(vec3 J, float z, vec3 w, vec3 w_cam) {{
    vec3 I = isinf(z) ? vec3(0.0) : J * exp_neg3(VIEW_C * z);
    float zs = min(z, g_to_surface);
#if defined(WITH_SCATTER) && defined(WITH_SUN)
    I += inscattered(g_sun, zs);
#endif
#if defined(WITH_SCATTER) && defined(WITH_SKY)
    I += inscattered(g_sky, zs);
#endif
#ifdef WITH_JMS
    I += inscattered(g_ms, zs);
#endif
#ifdef WITH_SKY
    if (isinf(z) && w.z > SNELL_COS) I += u_Esky / SNELL_SIN2 * exp_neg3(VIEW_C * g_to_surface);
#endif
    return I;
}}
#if defined(WITH_SCATTER) && LAMPS > 0
// The lamps' single scattering along the pixel's ray up to ray_end(z) of a sample (lamps.lamp_backscatter): the
// resolve calls it once a pixel where its samples' ray ends agree within LAMP_Z_SPREAD, else once a sample.
#define PIXEL_TERMS
const float LAMP_Z_SPREAD = {LAMP_Z_SPREAD!r};
float ray_end(float z) {{ return min(z, g_to_surface); }}
vec3 pixel_terms(float zs, vec3 w_cam) {{
    vec3 I = vec3(0.0);
    float kmin = 1e30;
    for (int c = 0; c < 3; ++c) if (u_b[c] > 0.0) kmin = min(kmin, u_K[c]);
    float t_end = min(zs, {CUTOFF_OPTICAL_DEPTH!r} / max(kmin, 1e-30));
    for (int l = 0; l < LAMPS; ++l) {{
        vec3 p = u_lamp_pos[l];
        float d_max = max(length(p), length(w_cam * t_end - p));
        vec2 seg = cone_interval(w_cam, p, u_lamp_dir[l], lamp_reach(u_lamp_cone[l], d_max), t_end);
        float tc = dot(w_cam, p);
        float h = max(length(w_cam * tc - p), {MIN_LAMP_DISTANCE_M!r});
        float u0 = atan(seg.x - tc, h);
        float du = (atan(seg.y - tc, h) - u0) / float({BACKSCATTER_NODES});
        vec3 acc = vec3(0.0);
        for (int i = 0; i < {BACKSCATTER_NODES}; ++i) {{
            float u = u0 + (float(i) + 0.5) * du;
            float t = tc + h * tan(u);
            vec3 to_x = w_cam * t - p;
            float r = max(length(to_x), {MIN_LAMP_DISTANCE_M!r});
            float f = hg(-dot(to_x, w_cam) / r, u_g) / h;
            acc += f * lamp_light(dot(to_x, u_lamp_dir[l]) / r, r, u_K * t, u_lamp_cone[l], u_lamp_energy[l], u_c, u_K,
                                  u_b, u_g);
        }}
        I += acc * du * u_b * (PI * u_lamp_I[l]);
    }}
    return I;
}}
#endif
"""
)
