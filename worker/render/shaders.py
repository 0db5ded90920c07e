"""GLSL sources of the renderer's passes: surface (in-air radiance, range), ids and/or range at pixel centres, resolve
(per-sample haze, nearest sample range)."""

# Every uniform any pass declares; a program's absent ones are simply not set.
UNIFORMS = (
    "u_cam_from_obj", "u_nrm_cam", "u_proj", "u_scale", "u_bias", "u_sun_cam", "u_sun", "u_ambient",
    "u_range_bounds", "u_id", "u_J", "u_R", "u_betaD", "u_betaB", "u_Binf", "u_only_sample", "u_srgb_thr",
)

# Range is interpolated at the pixel centre even for multisample coverage (no per-sample shading); a sample that
# covers a silhouette whose pixel centre lies off the triangle gets an extrapolated value, unbounded on receding
# surfaces. Clamping to the object's bounding-sphere range bounds that error by the object's size.
# Every pass shares this vertex stage, so a surface lands on exactly the same pixels and ranges in each pass.
VERTEX = """
#version 330 core
layout(location = 0) in vec3 a_pos;
layout(location = 1) in vec3 a_nrm;
layout(location = 2) in vec3 a_col;
uniform mat4 u_cam_from_obj;   // KITTI camera frame (x right, y down, z forward), metres
uniform mat3 u_nrm_cam;
uniform mat4 u_proj;
out vec3 v_pos;
out vec3 v_nrm;
out vec3 v_col;
invariant gl_Position;
void main() {
    vec4 p = u_cam_from_obj * vec4(a_pos, 1.0);
    v_pos = p.xyz;
    v_nrm = u_nrm_cam * a_nrm;
    v_col = a_col;
    gl_Position = u_proj * p;
}
"""

# In-air radiance J (linear RGB) of a Lambertian surface under a sun and an ambient term, lit from both sides.
SURFACE = """
#version 330 core
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
uniform vec3 u_scale;
uniform vec3 u_bias;
uniform vec2 u_range_bounds;   // nearest and farthest range of the object's bounding sphere, metres
uniform vec3 u_sun_cam;        // unit vector towards the sun, camera frame
uniform float u_sun;
uniform float u_ambient;
layout(location = 0) out vec4 o_J;
#ifdef WITH_RANGE
layout(location = 1) out float o_range;
#endif
void main() {
    float len = length(v_nrm);
    vec3 n = len > 1e-20 ? v_nrm / len : -normalize(v_pos);
    if (dot(n, v_pos) > 0.0) n = -n;   // face the camera: thin sheets are seen from both sides
    vec3 albedo = clamp(v_col * u_scale + u_bias, 0.0, 1.0);
    // J is the in-air image (the paper's J): radiance in the sensor's range [0, 1], so clean/ is J exactly.
    o_J = vec4(clamp(albedo * (u_ambient + u_sun * max(dot(n, u_sun_cam), 0.0)), 0.0, 1.0), 1.0);
#ifdef WITH_RANGE
    o_range = clamp(length(v_pos), u_range_bounds.x, u_range_bounds.y);
#endif
}
"""

# Instance ids (0 = terrain) and/or range at pixel centres (single sample): ids at location 0 when drawn, range
# after them.
IDS = """
#version 330 core
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
uniform uint u_id;
uniform vec2 u_range_bounds;
#ifdef WITH_IDS
layout(location = 0) out uint o_id;
#endif
#ifdef WITH_RANGE
layout(location = RANGE_LOCATION) out float o_range;
#endif
void main() {
#ifdef WITH_IDS
    o_id = u_id;
#endif
#ifdef WITH_RANGE
    o_range = clamp(length(v_pos), u_range_bounds.x, u_range_bounds.y);
#endif
}
"""

FULLSCREEN = """
#version 330 core
void main() {
    // One triangle that covers the viewport.
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

# Averages the samples of one output pixel in linear light; with water, each sample is hazed with its own range
# before averaging, so thin spines against open water blend correctly.
# Depth (shadow maps) or stencil (coverage counts) only: no colour is written.
DEPTH_ONLY = """
#version 330 core
void main() {}
"""

RESOLVE = """
#version 330 core
#if SAMPLES > 1
uniform sampler2DMS u_J;
uniform sampler2DMS u_R;
#define FETCH(t, q, s) texelFetch(t, q, s)
#else
uniform sampler2D u_J;
uniform sampler2D u_R;
#define FETCH(t, q, s) texelFetch(t, q, 0)
#endif
uniform vec3 u_betaD;
uniform vec3 u_betaB;
uniform vec3 u_Binf;
uniform int u_only_sample;     // >= 0: output that one sample (audits); < 0: the average
layout(location = 0) out vec4 o_img;
#ifdef SRGB8_OUT
SRGB8_FUNCTION
layout(location = NAN_LOCATION) out float o_nan;   // 1 where the pixel's linear colour was NaN
#endif
#ifdef WITH_CLEAN
layout(location = 1) out vec4 o_clean;
#endif
#ifdef WITH_SAMPLE_RANGE
layout(location = 1) out vec4 o_range;
#endif
#ifdef WITH_NEAREST
layout(location = NEAREST_LOCATION) out float o_nearest;   // nearest range of any sample, +inf if none hits
#endif
HAZE_FUNCTION
#ifdef PHYSICAL
uniform mat3 u_K_inv;
uniform mat3 u_world_from_cam;
#endif
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec3 acc = vec3(0.0);
    vec3 clean = vec3(0.0);
    // Any sample will do to start the minimum: an uncovered one holds the +inf its buffer was cleared to.
    float nearest = FETCH(u_R, px * SUPERSAMPLE, 0).r;
    float n = 0.0;
#ifdef PHYSICAL
    // The view ray through the pixel centre (pixel centres at integer coordinates, rows already in image order).
    vec3 w_cam = normalize(u_K_inv * vec3(vec2(px), 1.0));
    vec3 w_world = u_world_from_cam * w_cam;
    water_pixel(w_world);
#endif
    for (int dy = 0; dy < SUPERSAMPLE; ++dy) {
        for (int dx = 0; dx < SUPERSAMPLE; ++dx) {
            ivec2 q = px * SUPERSAMPLE + ivec2(dx, dy);
            for (int s = 0; s < SAMPLES; ++s) {
                int k = (dy * SUPERSAMPLE + dx) * SAMPLES + s;
                if (u_only_sample >= 0 && k != u_only_sample) continue;
                vec3 J = FETCH(u_J, q, s).rgb;
                clean += J;
#ifdef WITH_HAZE
                float z = FETCH(u_R, q, s).r;
                acc += haze(J, z, u_betaD, u_betaB, u_Binf);
#elif defined(PHYSICAL)
                acc += water(J, FETCH(u_R, q, s).r, w_world, w_cam);
#else
                acc += J;
#endif
#ifdef WITH_SAMPLE_RANGE
                o_range = vec4(FETCH(u_R, q, s).r, 0.0, 0.0, 1.0);
#endif
#ifdef WITH_NEAREST
                nearest = min(nearest, FETCH(u_R, q, s).r);
#endif
                n += 1.0;
            }
        }
    }
#ifdef SRGB8_OUT
    o_img = srgb8(acc / n);
    o_nan = o_img.a;
#else
    o_img = vec4(acc / n, 1.0);
#endif
#ifdef WITH_CLEAN
    o_clean = vec4(clean / n, 1.0);
#endif
#ifdef WITH_NEAREST
    o_nearest = nearest;
#endif
}
"""


def variant(source: str, **defines: object) -> str:
    """The source with `#define NAME VALUE` lines inserted after `#version` (True -> bare define, False -> none)."""
    head, rest = source.lstrip().split("\n", 1)
    lines = [f"#define {k} {'' if v is True else v}".rstrip() for k, v in defines.items() if v is not False]
    return "\n".join([head, *lines, rest])
