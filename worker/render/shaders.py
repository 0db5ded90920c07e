"""GLSL sources of the renderer's passes: surface (in-air radiance, range), ids and/or range at pixel centres, resolve
(per-sample haze, nearest sample range)."""

from seasynth.worker.render import materials

# Every uniform any pass declares; a program's absent ones are simply not set.
UNIFORMS = (
    "u_cam_from_obj", "u_nrm_cam", "u_proj", "u_scale", "u_bias", "u_sun_cam", "u_sun", "u_ambient",
    "u_range_bounds", "u_id", "u_J", "u_D", "u_depth", "u_sample_pos", "u_K_inv", "u_betaD", "u_betaB", "u_Binf",
    "u_only_sample", "u_srgb_thr",
    "u_size", *materials.UNIFORMS,
)

# The ids pass's range is interpolated at the pixel centre; clamping to the object's bounding-sphere range bounds
# any interpolation error by the object's size. (The surface pass writes no range: its resolve derives each sample's
# range from the sample's depth, worker.render.depth.)
# Every pass shares this vertex stage, so a surface lands on exactly the same pixels and ranges in each pass.
VERTEX = (
    """
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
"""
    + materials.VERTEX_IN
    + """
void main() {
    vec4 p = u_cam_from_obj * vec4(a_pos, 1.0);
    v_pos = p.xyz;
    v_nrm = u_nrm_cam * a_nrm;
    v_col = a_col;
    gl_Position = u_proj * p;
"""
    + materials.VERTEX_MAIN
    + """
}
"""
)

# A surface's normal facing the camera and its albedo (textured: per pixel, worker.render.materials), as the
# surface passes (this one and worker.light.glsl.SURFACE) begin.
SURFACE_BEGIN = """
    float len = length(v_nrm);
    vec3 n = len > 1e-20 ? v_nrm / len : -normalize(v_pos);
    if (dot(n, v_pos) > 0.0) n = -n;   // face the camera: thin sheets are seen from both sides
    float occlusion = 1.0;
#ifdef TEXTURED
    vec3 albedo = clamp(v_col * textured_albedo(n, occlusion) * u_scale + u_bias, 0.0, 1.0);
#else
    vec3 albedo = clamp(v_col * u_scale + u_bias, 0.0, 1.0);
#endif
"""

# In-air radiance J (linear RGB) of a Lambertian surface under a sun and an ambient term, lit from both sides.
SURFACE = (
    """
#version 330 core
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_col;
uniform vec3 u_scale;
uniform vec3 u_bias;
uniform vec3 u_sun_cam;        // unit vector towards the sun, camera frame
uniform float u_sun;
uniform float u_ambient;
layout(location = 0) out vec4 o_J;
"""
    + materials.FRAGMENT
    + """
void main() {
"""
    + SURFACE_BEGIN
    + """
    // J is the in-air image (the paper's J): radiance in the sensor's range [0, 1], so clean/ is J exactly.
    o_J = vec4(clamp(albedo * (u_ambient * occlusion + u_sun * max(dot(n, u_sun_cam), 0.0)), 0.0, 1.0), 1.0);
}
"""
)

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

# Depth (shadow maps) or stencil (coverage counts) only: no colour is written.
DEPTH_ONLY = """
#version 330 core
void main() {}
"""

# Averages the samples of one output pixel in linear light; with water, each sample is hazed with its own range
# before averaging, so thin spines against open water blend correctly. The same source runs as a fragment shader
# over a full-screen triangle or, with COMPUTE (GL 4.3), as a compute shader writing its outputs as images: on
# GPUs whose graphics units are few (an H100 runs fragment shaders on a small part of its chip) the compute
# shader runs on every unit. Both store the same values in the same formats.
RESOLVE = """
#version 330 core
#if SAMPLES > 1
uniform sampler2DMS u_J;
uniform sampler2DMS u_D;
#define FETCH(t, q, s) texelFetch(t, q, s)
#else
uniform sampler2D u_J;
uniform sampler2D u_D;
#define FETCH(t, q, s) texelFetch(t, q, 0)
#endif
uniform vec3 u_betaD;
uniform vec3 u_betaB;
uniform vec3 u_Binf;
uniform int u_only_sample;     // >= 0: output that one sample (audits); < 0: the average
#ifdef COMPUTE
layout(local_size_x = 8, local_size_y = 8) in;
uniform ivec2 u_size;
layout(binding = 0, IMG_FORMAT) writeonly uniform image2D u_out_img;
#define OUT_IMG(v) imageStore(u_out_img, px, v)
#else
layout(location = 0) out vec4 o_img;
#define OUT_IMG(v) o_img = v
#endif
#ifdef SRGB8_OUT
SRGB8_FUNCTION
#ifdef COMPUTE
layout(binding = NAN_LOCATION, r8) writeonly uniform image2D u_out_nan;
#define OUT_NAN(v) imageStore(u_out_nan, px, vec4(v))
#else
layout(location = NAN_LOCATION) out float o_nan;   // 1 where the pixel's linear colour was NaN
#define OUT_NAN(v) o_nan = v
#endif
#endif
#if defined(WITH_CLEAN) || defined(WITH_SAMPLE_RANGE)
#ifdef COMPUTE
layout(binding = 1, rgba32f) writeonly uniform image2D u_out_second;
#define OUT_SECOND(v) imageStore(u_out_second, px, v)
#else
layout(location = 1) out vec4 o_second;   // the clean image, or one sample's range (audits)
#define OUT_SECOND(v) o_second = v
#endif
#endif
#ifdef WITH_NEAREST
#ifdef COMPUTE
layout(binding = NEAREST_LOCATION, r32f) writeonly uniform image2D u_out_nearest;
#define OUT_NEAREST(v) imageStore(u_out_nearest, px, vec4(v))
#else
layout(location = NEAREST_LOCATION) out float o_nearest;   // nearest range of any sample, +inf if none hits
#define OUT_NEAREST(v) o_nearest = v
#endif
#endif
#if defined(RANGE_IN) || defined(PHYSICAL)
uniform mat3 u_K_inv;
#endif
#ifdef RANGE_IN
RANGE_FUNCTION
#endif
HAZE_FUNCTION
#ifdef PHYSICAL
uniform mat3 u_world_from_cam;
#endif
void main() {
#ifdef COMPUTE
    ivec2 px = ivec2(gl_GlobalInvocationID.xy);
    if (px.x >= u_size.x || px.y >= u_size.y) return;
#else
    ivec2 px = ivec2(gl_FragCoord.xy);
#endif
    vec3 acc = vec3(0.0);
    vec3 clean = vec3(0.0);
    float nearest = uintBitsToFloat(0x7F800000u);
    float n = 0.0;
#ifdef PIXEL_TERMS
    float ends[SUPERSAMPLE * SUPERSAMPLE * SAMPLES];   // the samples' ray ends
    float end_lo = uintBitsToFloat(0x7F800000u), end_hi = 0.0, end_sum = 0.0;
#endif
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
#ifdef RANGE_IN
                // Depth still 0.0 (its clear, reversed depth): nothing was drawn at this sample, so range +inf and
                // colour 0. The surface pass does not clear its colour where it draws for range: what a previous
                // frame left there is replaced.
                float d = FETCH(u_D, q, s).r;
                bool drawn = d > 0.0;
                float z = drawn ? sample_range(q, s, d) : uintBitsToFloat(0x7F800000u);
                if (!drawn) J = vec3(0.0);
#endif
                clean += J;
#ifdef WITH_HAZE
                acc += haze(J, z, u_betaD, u_betaB, u_Binf);
#elif defined(PHYSICAL)
                acc += water(J, z, w_world, w_cam);
#ifdef PIXEL_TERMS
                ends[k] = ray_end(z);
                end_lo = min(end_lo, ends[k]);
                end_hi = max(end_hi, ends[k]);
                end_sum += ends[k];
#endif
#else
                acc += J;
#endif
#ifdef WITH_SAMPLE_RANGE
                OUT_SECOND(vec4(z, 0.0, 0.0, 1.0));
#endif
#ifdef WITH_NEAREST
                nearest = min(nearest, z);
#endif
                n += 1.0;
            }
        }
    }
#ifdef PIXEL_TERMS
    // Terms smooth in a sample's ray end (the lamps' scattering): once at the mean end where the pixel's samples
    // agree within LAMP_Z_SPREAD (all of them, open water included, on most pixels), else once a sample.
    if (end_hi == end_lo) {
        acc += n * pixel_terms(end_lo, w_cam);
    } else if (end_hi - end_lo <= LAMP_Z_SPREAD * end_lo) {
        acc += n * pixel_terms(end_sum / n, w_cam);
    } else {
        for (int k = 0; k < SUPERSAMPLE * SUPERSAMPLE * SAMPLES; ++k)
            if (u_only_sample < 0 || k == u_only_sample) acc += pixel_terms(ends[k], w_cam);
    }
#endif
#ifdef SRGB8_OUT
    vec4 codes = srgb8(acc / n);
    OUT_IMG(codes);
    OUT_NAN(codes.a);
#else
    OUT_IMG(vec4(acc / n, 1.0));
#endif
#ifdef WITH_CLEAN
    OUT_SECOND(vec4(clean / n, 1.0));
#endif
#ifdef WITH_NEAREST
    OUT_NEAREST(nearest);
#endif
}
"""


# What a compute shader needs of a context that is older than GL 4.3 (pyrender asks EGL for 4.1) but has it as
# extensions.
COMPUTE_EXTENSIONS = ("GL_ARB_compute_shader", "GL_ARB_shader_image_load_store", "GL_ARB_shading_language_420pack")


def context_version(GL) -> tuple[int, int]:
    """(major, minor) GL version of the current context."""
    return int(GL.glGetIntegerv(GL.GL_MAJOR_VERSION)), int(GL.glGetIntegerv(GL.GL_MINOR_VERSION))


def context_has(GL, extensions: tuple[str, ...]) -> bool:
    """Whether the current context exposes every one of `extensions`."""
    have = {GL.glGetStringi(GL.GL_EXTENSIONS, k).decode() for k in range(int(GL.glGetIntegerv(GL.GL_NUM_EXTENSIONS)))}
    return all(e in have for e in extensions)


def compute_header(GL) -> str | None:
    """The first lines of a compute shader in the current context: `#version 430 core` on GL >= 4.3, else #version
    410 with the extensions that bring compute shaders and image stores; None where the context has neither."""
    if context_version(GL) >= (4, 3):
        return "#version 430 core"
    if not context_has(GL, COMPUTE_EXTENSIONS):
        return None
    return "\n".join(["#version 410 core", *(f"#extension {e} : require" for e in COMPUTE_EXTENSIONS)])


def variant(source: str, **defines: object) -> str:
    """The source with `#define NAME VALUE` lines inserted after `#version` (True -> bare define, False -> none)."""
    head, rest = source.lstrip().split("\n", 1)
    lines = [f"#define {k} {'' if v is True else v}".rstrip() for k, v in defines.items() if v is not False]
    return "\n".join([head, *lines, rest])
