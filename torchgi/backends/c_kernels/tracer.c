/* The compiled path tracer: torchgi.render's "path" integrator, one sample at a time, on embree.
 *
 * Built into the same library as native.c (c_kernels/build.py) and called through ctypes, which
 * releases the GIL: the pixels of a call run on OpenMP threads, each pixel's samples in order,
 * so neither the thread count nor how the pixels are cut into calls changes a bit. The maths is
 * that of torchgi/render/integrators/path.py with every skip of docs/design.md (Skips) on (paths that miss
 * or die stop; no BSDF ray from a diffuse last vertex; light types the scene lacks are never
 * sampled), the same random dimension for each decision (sampler.py's counter-based hash), and
 * the film of render/film.py: blocks of BLOCK samples, a block's sum and its colour M2 about the
 * block mean in double, blocks merged in order by Chan's update.
 *
 * Embree 4 is the library embreex ships: its entry points come in as function pointers
 * (c_kernels/embree.py), so nothing here links against it or needs its
 * headers; the few types below are embree 4's RTCRay / RTCRayHit layout (rtcore_ray.h).
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#if defined(_OPENMP)
#include <omp.h>
#endif

#define PT_INLINE static inline __attribute__((always_inline))
#define PT_BLOCK 1024          /* film.BLOCK */
#define PT_INVALID 0xFFFFFFFFu /* RTC_INVALID_GEOMETRY_ID */
#define PT_PI 3.14159265358979323846f
#define PT_SHADOW_END (1.0f - 1e-4f) /* path._SHADOW_END */

/* ---------------------------------------------------------------- embree 4 */
typedef struct __attribute__((aligned(16))) {
    float org_x, org_y, org_z, tnear;
    float dir_x, dir_y, dir_z, time;
    float tfar;
    unsigned int mask, id, flags;
} pt_ray;

typedef struct __attribute__((aligned(16))) {
    pt_ray ray;
    float Ng_x, Ng_y, Ng_z, u, v;
    unsigned int primID, geomID;
    unsigned int inst[8]; /* instID[] (and instPrimID[] in 4.3+): room for any build's levels */
} pt_rayhit;

typedef void *(*new_device_fn)(const char *);
typedef void *(*new_scene_fn)(void *);
typedef void *(*new_geometry_fn)(void *, int);
typedef void *(*new_buffer_fn)(void *, int, unsigned int, int, size_t, size_t);
typedef void (*handle_fn)(void *);
typedef unsigned int (*attach_fn)(void *, void *);
typedef void (*intersect_fn)(void *, pt_rayhit *, void *);
typedef void (*occluded_fn)(void *, pt_ray *, void *);
typedef int (*error_fn)(void *);

static struct {
    new_device_fn new_device;
    new_scene_fn new_scene;
    new_geometry_fn new_geometry;
    new_buffer_fn new_buffer;
    handle_fn commit_geometry;
    attach_fn attach;
    handle_fn release_geometry;
    handle_fn commit_scene;
    handle_fn release_scene;
    handle_fn release_device;
    intersect_fn intersect;
    occluded_fn occluded;
    error_fn error;
} E;

/* fns: the 13 entry points in the order of the struct above (accel.EMBREE_FUNCTIONS) */
void torchgi_embree_init(void **fns) { memcpy(&E, fns, sizeof(E)); }

typedef struct {
    void *device, *scene;
} pt_scene;

/* A BVH over tri (T, 3, 3) float32: vertex 3t + k is corner k of triangle t. NULL on failure. */
void *torchgi_scene_new(const float *tri, long long T) {
    if (!E.new_device) return NULL; /* torchgi_embree_init not called */
    pt_scene *s = calloc(1, sizeof(pt_scene));
    if (!s) return NULL;
    s->device = E.new_device(NULL);
    if (!s->device) { free(s); return NULL; }
    s->scene = E.new_scene(s->device);
    void *g = E.new_geometry(s->device, 0 /* RTC_GEOMETRY_TYPE_TRIANGLE */);
    float *v = E.new_buffer(g, 1 /* VERTEX */, 0, 0x9003 /* FLOAT3 */, 3 * sizeof(float), (size_t)(3 * T));
    unsigned int *ix = E.new_buffer(g, 0 /* INDEX */, 0, 0x5003 /* UINT3 */, 3 * sizeof(unsigned int), (size_t)T);
    if (!v || !ix) { E.release_geometry(g); E.release_scene(s->scene); E.release_device(s->device); free(s); return NULL; }
    memcpy(v, tri, (size_t)T * 9 * sizeof(float));
    for (long long i = 0; i < 3 * T; i++) ix[i] = (unsigned int)i;
    E.commit_geometry(g);
    E.attach(s->scene, g);
    E.release_geometry(g);
    E.commit_scene(s->scene);
    if (E.error(s->device) != 0) { E.release_scene(s->scene); E.release_device(s->device); free(s); return NULL; }
    return s;
}

void torchgi_scene_free(void *handle) {
    pt_scene *s = handle;
    if (!s) return;
    E.release_scene(s->scene);
    E.release_device(s->device);
    free(s);
}

/* ---------------------------------------------------------------- the render call */
/* What a call reads (c_kernels.path fills it; lights.Tables' rows, transposed to one row per
 * triangle: tri (T, 12), light (L, 21)). */
typedef struct {
    const float *tri;
    const float *light;
    const float *cdf;
    const float *points, *intensities; /* (P, 3) */
    const float *sky;                  /* (3), NULL without a sky */
    long long T;
    int L, P, any_glossy;
    float eps; /* accel.offset's distance */
    float origin[3], basis[9]; /* camera position; right, up, forward (rows) */
    float tan_x, tan_y;
    int width, height;
    int bounces, roulette_from, record; /* record: 0 all, 1 direct, 2 indirect */
    uint32_t head;                      /* sampler.sample_keys' (seed, stream) key */
    double *profile; /* NULL, or per thread: seconds in rtcIntersect1, in rtcOccluded1, and their calls */
} pt_render;

/* the calling thread's row of pt_render.profile (NULL: not profiling) */
static __thread double *pt_profile;

PT_INLINE double pt_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static void profile_on(const pt_render *R) {
    int thread = 0;
#if defined(_OPENMP)
    thread = omp_get_thread_num();
#endif
    pt_profile = R->profile ? R->profile + 4 * thread : NULL;
}

/* row offsets of lights.Tables */
enum { T_NORMAL = 0, T_EMISSION = 3, T_PDF = 6, T_ALBEDO = 7, T_ALPHA = 10, T_GLOSSY = 11, T_TEXTURE = 12,
       T_TEXTURE_SCALE = 13, T_ALBEDO2 = 14, T_ROWS = 17, L_V0 = 17, L_E1 = 20, L_E2 = 23, L_ROWS = 26 };
enum { D_LIGHT = 0, D_SKY = 3, D_BSDF = 5, D_ROULETTE = 7, D_PER_VERTEX = 8 }; /* integrators/common.py */

PT_INLINE uint32_t mix32(uint32_t x) {
    x = ((x >> 16) ^ x) * 0x45D9F3Bu;
    x = ((x >> 16) ^ x) * 0x45D9F3Bu;
    return (x >> 16) ^ x;
}

/* sampler.uniform: dimension d of a sample's key, in [0, 1 - 2^-24] */
PT_INLINE float uniform1(uint32_t key, int d) {
    const uint32_t h = mix32(key ^ mix32((uint32_t)d * 0x27D4EB2Fu + 0x165667B1u));
    return (float)((h >> 8) & 0xFFFFFFu) * (1.0f / 16777216.0f);
}

PT_INLINE float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
PT_INLINE float max3(const float *a) { return fmaxf(a[0], fmaxf(a[1], a[2])); }
PT_INLINE float power(float a, float b) { const float a2 = a * a; return a2 > 0 ? a2 / (a2 + b * b) : 0.0f; }

/* materials.frame (Duff et al. 2017) and to_world */
PT_INLINE void to_world(const float *n, const float *l, float *w) {
    const float sign = n[2] >= 0 ? 1.0f : -1.0f, a = -1.0f / (sign + n[2]), b = n[0] * n[1] * a;
    const float t[3] = {1.0f + sign * n[0] * n[0] * a, sign * b, -sign * n[0]};
    const float s[3] = {b, sign + n[1] * n[1] * a, -n[1]};
    for (int k = 0; k < 3; k++) w[k] = t[k] * l[0] + s[k] * l[1] + n[k] * l[2];
}

/* materials.cosine_hemisphere: local direction, pdf = z / pi */
PT_INLINE void cosine_hemisphere(float u0, float u1, float *l) {
    const float r = sqrtf(u0), phi = (2.0f * PT_PI) * u1;
    l[0] = r * cosf(phi);
    l[1] = r * sinf(phi);
    l[2] = sqrtf(fmaxf(1.0f - u0, 0.0f));
}

PT_INLINE float ggx_g1(float c, float a) {
    const float c2 = fmaxf(c * c, 1e-12f), tan2 = fmaxf(1.0f - c2, 0.0f) / c2;
    return 2.0f / (1.0f + sqrtf(1.0f + a * a * tan2));
}

typedef struct {
    float p[3], o[3], n[3], wi[3], albedo[3], alpha;
    int glossy;
} pt_vertex;

/* materials.bsdf_eval: f cos_o (scalar, times albedo by the caller) and the pdf of wo */
PT_INLINE float bsdf_eval(const pt_vertex *s, const float *wo, float *pdf) {
    const float cos_o = fmaxf(dot3(s->n, wo), 0.0f);
    if (!s->glossy) { *pdf = cos_o * (1.0f / PT_PI); return *pdf; }
    if (!(cos_o > 0)) { *pdf = 0.0f; return 0.0f; }
    const float cos_i = fmaxf(dot3(s->n, s->wi), 1e-7f);
    float h[3] = {s->wi[0] + wo[0], s->wi[1] + wo[1], s->wi[2] + wo[2]};
    const float inv = 1.0f / sqrtf(fmaxf(dot3(h, h), 1e-20f));
    for (int k = 0; k < 3; k++) h[k] *= inv;
    const float cos_h = dot3(s->n, h), a2 = s->alpha * s->alpha, c2 = cos_h * cos_h;
    const float den = c2 * (a2 - 1.0f) + 1.0f;
    const float d = cos_h > 0 ? a2 / (PT_PI * den * den) : 0.0f;
    *pdf = d * cos_h / (4.0f * fmaxf(fabsf(dot3(wo, h)), 1e-7f));
    return d * ggx_g1(cos_i, s->alpha) * ggx_g1(cos_o, s->alpha) / (4.0f * cos_i);
}

/* materials.bsdf_sample: wo, the weight f cos_o / pdf (3) and the pdf */
PT_INLINE float bsdf_sample(const pt_vertex *s, float u0, float u1, float *wo, float *weight) {
    float l[3];
    if (!s->glossy) {
        cosine_hemisphere(u0, u1, l);
        to_world(s->n, l, wo);
        for (int k = 0; k < 3; k++) weight[k] = s->albedo[k];
        return l[2] * (1.0f / PT_PI);
    }
    const float a2 = s->alpha * s->alpha, cos2 = (1.0f - u0) / (1.0f + (a2 - 1.0f) * u0);
    const float sin_h = sqrtf(fmaxf(1.0f - cos2, 0.0f)), phi = (2.0f * PT_PI) * u1;
    l[0] = sin_h * cosf(phi);
    l[1] = sin_h * sinf(phi);
    l[2] = sqrtf(cos2);
    float h[3];
    to_world(s->n, l, h);
    const float c = 2.0f * dot3(s->wi, h);
    for (int k = 0; k < 3; k++) wo[k] = c * h[k] - s->wi[k];
    float pdf;
    const float f = bsdf_eval(s, wo, &pdf);
    const float w = pdf > 0 ? f / fmaxf(pdf, 1e-20f) : 0.0f;
    for (int k = 0; k < 3; k++) weight[k] = s->albedo[k] * w;
    return pdf;
}

/* closest hit within tmax: the triangle (-1 on a miss) and its distance */
PT_INLINE long long trace(void *scene, const float *o, const float *d, float *t) {
    pt_rayhit r;
    r.ray.org_x = o[0], r.ray.org_y = o[1], r.ray.org_z = o[2], r.ray.tnear = 0.0f;
    r.ray.dir_x = d[0], r.ray.dir_y = d[1], r.ray.dir_z = d[2], r.ray.time = 0.0f;
    r.ray.tfar = INFINITY, r.ray.mask = 0xFFFFFFFFu, r.ray.id = 0, r.ray.flags = 0;
    r.geomID = r.primID = PT_INVALID;
    r.inst[0] = PT_INVALID;
    if (pt_profile) {
        const double t0 = pt_now();
        E.intersect(scene, &r, NULL);
        pt_profile[0] += pt_now() - t0;
        pt_profile[2] += 1;
    } else {
        E.intersect(scene, &r, NULL);
    }
    if (r.geomID == PT_INVALID) return -1;
    *t = r.ray.tfar;
    return (long long)r.primID;
}

PT_INLINE int occluded(void *scene, const float *o, const float *d, float tmax) {
    pt_ray r;
    r.org_x = o[0], r.org_y = o[1], r.org_z = o[2], r.tnear = 0.0f;
    r.dir_x = d[0], r.dir_y = d[1], r.dir_z = d[2], r.time = 0.0f;
    r.tfar = tmax, r.mask = 0xFFFFFFFFu, r.id = 0, r.flags = 0;
    if (pt_profile) {
        const double t0 = pt_now();
        E.occluded(scene, &r, NULL);
        pt_profile[1] += pt_now() - t0;
        pt_profile[3] += 1;
    } else {
        E.occluded(scene, &r, NULL);
    }
    return r.tfar < 0; /* embree sets -inf on a hit */
}

/* materials.lattice_hash: a value in [0, 1) for an integer lattice point */
PT_INLINE float lattice_hash(int64_t i, int64_t j, int64_t k) {
    uint32_t h = ((uint32_t)i * 0x8DA6B343u) ^ ((uint32_t)j * 0xD8163841u) ^ ((uint32_t)k * 0xCB1AB31Fu);
    h ^= h >> 16;
    h *= 0x7FEB352Du;
    h ^= h >> 15;
    h *= 0x846CA68Bu;
    h ^= h >> 16;
    return (float)(h >> 8) * (1.0f / 16777216.0f);
}

/* materials.texture_weight: the second colour's weight of texture code at the scaled point q */
PT_INLINE float texture_weight(int code, const float *q) {
    const float f[3] = {floorf(q[0]), floorf(q[1]), floorf(q[2])};
    const int64_t c[3] = {(int64_t)f[0], (int64_t)f[1], (int64_t)f[2]};
    if (code == 1) return (float)((c[0] + c[1] + c[2]) & 1);
    if (code == 2) return (float)(((int64_t)floorf(q[0] + q[2])) & 1);
    if (code != 3) return 0.0f;
    float w[3];
    for (int a = 0; a < 3; a++) { const float x = q[a] - f[a]; w[a] = x * x * (3.0f - 2.0f * x); }
    float noise = 0.0f;
    for (int corner = 0; corner < 8; corner++) {
        const int d0 = corner & 1, d1 = (corner >> 1) & 1, d2 = (corner >> 2) & 1;
        float weight = 1.0f;
        weight = weight * (d0 ? w[0] : 1.0f - w[0]);
        weight = weight * (d1 ? w[1] : 1.0f - w[1]);
        weight = weight * (d2 ? w[2] : 1.0f - w[2]);
        noise = noise + weight * lattice_hash(c[0] + d0, c[1] + d1, c[2] + d2);
    }
    return noise;
}

/* common.surface: the vertex where a ray along d met triangle prim at p */
PT_INLINE void vertex(const pt_render *R, long long prim, const float *p, const float *d, pt_vertex *s) {
    const float *row = R->tri + prim * T_ROWS;
    const float flip = (row[T_NORMAL] * -d[0] + row[T_NORMAL + 1] * -d[1] + row[T_NORMAL + 2] * -d[2]) < 0 ? -1.0f : 1.0f;
    for (int k = 0; k < 3; k++) {
        s->p[k] = p[k];
        s->n[k] = flip * row[T_NORMAL + k];
        s->wi[k] = -d[k];
        s->albedo[k] = row[T_ALBEDO + k];
    }
    for (int k = 0; k < 3; k++) s->o[k] = p[k] + s->n[k] * R->eps;
    s->alpha = row[T_ALPHA];
    s->glossy = R->any_glossy && row[T_GLOSSY] > 0;
    if (row[T_TEXTURE] > 0) { /* materials.textured_albedo */
        const float q[3] = {p[0] * row[T_TEXTURE_SCALE], p[1] * row[T_TEXTURE_SCALE], p[2] * row[T_TEXTURE_SCALE]};
        const float t = texture_weight((int)row[T_TEXTURE], q);
        for (int k = 0; k < 3; k++) s->albedo[k] = s->albedo[k] + t * (row[T_ALBEDO2 + k] - s->albedo[k]);
    }
}

/* lights.sample_area_light's choice: the first light whose cdf exceeds u (searchsorted right) */
PT_INLINE int pick_light(const float *cdf, int L, float u) {
    int lo = 0, hi = L;
    while (lo < hi) {
        const int mid = (lo + hi) >> 1;
        if (cdf[mid] <= u) lo = mid + 1; else hi = mid;
    }
    return lo < L - 1 ? lo : L - 1;
}

/* path._next_event: light sampled at s into acc; w_mis: 0 weight 1 (diffuse last vertex), else MIS */
static void next_event(const pt_render *R, void *scene, const pt_vertex *s, const float *beta, uint32_t key, int base,
                       int mis, float *acc) {
    float pdf_bsdf, wl[3];
    if (R->L > 0) {
        const float *row = R->light + (size_t)pick_light(R->cdf, R->L, uniform1(key, base + D_LIGHT)) * L_ROWS;
        const float su = sqrtf(uniform1(key, base + D_LIGHT + 1)), u2 = uniform1(key, base + D_LIGHT + 2);
        const float b1 = su * (1.0f - u2), b2 = su * u2;
        float to[3];
        for (int k = 0; k < 3; k++) to[k] = row[L_V0 + k] + row[L_E1 + k] * b1 + row[L_E2 + k] * b2 - s->p[k];
        const float dist2 = dot3(to, to), inv = 1.0f / sqrtf(dist2);
        for (int k = 0; k < 3; k++) wl[k] = to[k] * inv;
        const float cos_l = -dot3(row + T_NORMAL, wl);
        const float f = bsdf_eval(s, wl, &pdf_bsdf);
        if (cos_l > 0 && f > 0 && max3(s->albedo) > 0) {
            const float pdf_light = row[T_PDF] * dist2 / fmaxf(cos_l, 1e-12f);
            const float w = (mis ? power(pdf_light, pdf_bsdf) : 1.0f) / pdf_light;
            if (!occluded(scene, s->o, wl, dist2 * inv * PT_SHADOW_END))
                for (int k = 0; k < 3; k++) acc[k] += beta[k] * s->albedo[k] * f * row[T_EMISSION + k] * w;
        }
    }
    for (int p = 0; p < R->P; p++) {
        float to[3];
        for (int k = 0; k < 3; k++) to[k] = R->points[3 * p + k] - s->p[k];
        const float dist2 = dot3(to, to), inv = 1.0f / sqrtf(dist2);
        for (int k = 0; k < 3; k++) wl[k] = to[k] * inv;
        const float f = bsdf_eval(s, wl, &pdf_bsdf);
        if (f > 0 && max3(s->albedo) > 0 && !occluded(scene, s->o, wl, dist2 * inv * PT_SHADOW_END))
            for (int k = 0; k < 3; k++) acc[k] += beta[k] * s->albedo[k] * f * R->intensities[3 * p + k] / dist2;
    }
    if (R->sky) {
        float l[3];
        cosine_hemisphere(uniform1(key, base + D_SKY), uniform1(key, base + D_SKY + 1), l);
        to_world(s->n, l, wl);
        const float pdf_sky = l[2] * (1.0f / PT_PI);
        const float f = bsdf_eval(s, wl, &pdf_bsdf);
        if (pdf_sky > 0 && f > 0 && max3(s->albedo) > 0) {
            const float w = (mis ? power(pdf_sky, pdf_bsdf) : 1.0f) / fmaxf(pdf_sky, 1e-20f);
            if (!occluded(scene, s->o, wl, INFINITY))
                for (int k = 0; k < 3; k++) acc[k] += beta[k] * s->albedo[k] * f * R->sky[k] * w;
        }
    }
}

/* path.radiance of one sample: out[0:3] emission, [3:6] direct, [6:9] indirect */
static void radiance(const pt_render *R, void *scene, uint32_t pixel, uint32_t sample, float *out) {
    memset(out, 0, 9 * sizeof(float));
    const uint32_t key = mix32(mix32(pixel ^ R->head) ^ sample);
    const uint32_t p = pixel % (uint32_t)(R->width * R->height);
    const float x = (float)(p % (uint32_t)R->width) + uniform1(key, 0);
    const float y = (float)(p / (uint32_t)R->width) + uniform1(key, 1);
    const float sx = (2.0f * R->tan_x / (float)R->width) * x - R->tan_x;
    const float sy = R->tan_y - (2.0f * R->tan_y / (float)R->height) * y;
    float d[3], pos[3], t = 0.0f;
    for (int k = 0; k < 3; k++) d[k] = R->basis[k] * sx + R->basis[3 + k] * sy + R->basis[6 + k];
    const float inv = 1.0f / sqrtf(dot3(d, d));
    for (int k = 0; k < 3; k++) d[k] *= inv;
    long long prim = trace(scene, R->origin, d, &t);
    if (R->record != 2) {
        if (prim >= 0 && R->L > 0) {
            const float *row = R->tri + prim * T_ROWS;
            if (dot3(row + T_NORMAL, d) < 0)
                for (int k = 0; k < 3; k++) out[k] += row[T_EMISSION + k];
        }
        if (prim < 0 && R->sky)
            for (int k = 0; k < 3; k++) out[k] += R->sky[k];
    }
    if (prim < 0) return;
    for (int k = 0; k < 3; k++) pos[k] = R->origin[k] + d[k] * t;
    float beta[3] = {1.0f, 1.0f, 1.0f};
    const int bounces = R->record == 1 ? 0 : R->bounces;
    const int emitters = R->L > 0 || R->sky != NULL;
    for (int depth = 1; depth <= bounces + 1; depth++) {
        const int last = depth == bounces + 1, base = 2 + D_PER_VERTEX * (depth - 1);
        float *rows = out + (depth == 1 ? 3 : 6);
        const int record_here = !(depth == 1 && R->record == 2);
        pt_vertex s;
        vertex(R, prim, pos, d, &s);
        float acc[3] = {0.0f, 0.0f, 0.0f};
        if (record_here) next_event(R, scene, &s, beta, key, base, !last || s.glossy, acc);
        if (last && !(s.glossy && emitters)) {  /* no BSDF ray from a diffuse last vertex */
            for (int k = 0; k < 3; k++) rows[k] += acc[k];
            break;
        }
        float wo[3], weight[3];
        const float pdf = bsdf_sample(&s, uniform1(key, base + D_BSDF), uniform1(key, base + D_BSDF + 1), wo, weight);
        for (int k = 0; k < 3; k++) beta[k] *= weight[k];
        int live = max3(beta) > 0;
        if (live && depth > R->roulette_from) {
            const float q = fminf(max3(beta), 0.95f);
            live = uniform1(key, base + D_ROULETTE) < q;
            if (live) for (int k = 0; k < 3; k++) beta[k] /= q;
        }
        prim = live ? trace(scene, s.o, wo, &t) : -1;
        if (live && record_here) {
            if (prim >= 0 && R->L > 0) {  /* an emitter's front face met by the BSDF ray */
                const float *row = R->tri + prim * T_ROWS;
                if (dot3(row + T_NORMAL, wo) < 0) {
                    const float cos_l = fmaxf(-dot3(row + T_NORMAL, wo), 1e-12f);
                    const float w = power(pdf, row[T_PDF] * t * t / cos_l);
                    for (int k = 0; k < 3; k++) acc[k] += beta[k] * row[T_EMISSION + k] * w;
                }
            }
            if (prim < 0 && R->sky) {
                const float w = power(pdf, fmaxf(dot3(s.n, wo), 0.0f) * (1.0f / PT_PI));
                for (int k = 0; k < 3; k++) acc[k] += beta[k] * R->sky[k] * w;
            }
        }
        for (int k = 0; k < 3; k++) rows[k] += acc[k];
        if (last || prim < 0) break;
        for (int k = 0; k < 3; k++) {
            pos[k] = s.o[k] + wo[k] * t;
            d[k] = wo[k];
        }
    }
}

/* One pixel's samples 0 .. n-1 into its film (film.Film.add_blocks): mean[12] and m2[3] */
static void pixel_film(const pt_render *R, void *scene, uint32_t pixel, long long n, double *mean, double *m2,
                       float *colour) {
    double count = 0.0;
    for (long long start = 0; start < n; start += PT_BLOCK) {
        const int nb = (int)(n - start < PT_BLOCK ? n - start : PT_BLOCK);
        double sum[12] = {0};
        for (int i = 0; i < nb; i++) {
            float v[9];
            radiance(R, scene, pixel, (uint32_t)(start + i), v);
            for (int k = 0; k < 9; k++) sum[k] += v[k];
            for (int k = 0; k < 3; k++) {
                colour[3 * i + k] = v[k] + v[3 + k] + v[6 + k];
                sum[9 + k] += colour[3 * i + k];
            }
        }
        double bm[12], bm2[3] = {0};
        for (int k = 0; k < 12; k++) bm[k] = sum[k] / nb;
        for (int i = 0; i < nb; i++)
            for (int k = 0; k < 3; k++) {
                const double dev = colour[3 * i + k] - bm[9 + k];
                bm2[k] += dev * dev;
            }
        const double na = count, total = na + nb;
        for (int k = 0; k < 12; k++) {
            const double delta = bm[k] - mean[k];
            if (k >= 9) m2[k - 9] += bm2[k - 9] + delta * delta * (na * nb / total);
            mean[k] += delta * (nb / total);
        }
        count = total;
    }
}

/* Pixels first + i0 .. first + i1 - 1 (global index b*H*W + y*W + x), counts[i] samples each:
 * mean (9, rows of `stride`) of emission, direct, indirect and var (3, rows of `stride`), the
 * variance of the colour's mean. */
static void film_pixels(const pt_render *R, void *scene, long long first, const long long *counts, long long stride,
                        long long i0, long long i1, double *mean, double *var, float *colour) {
    profile_on(R);
    for (long long i = i0; i < i1; i++) {
        double m[12] = {0}, m2[3] = {0};
        pixel_film(R, scene, (uint32_t)(first + i), counts[i], m, m2, colour);
        for (int k = 0; k < 9; k++) mean[k * stride + i] = m[k];
        const double n = (double)counts[i];
        for (int k = 0; k < 3; k++) var[k * stride + i] = n > 1 ? m2[k] / (n * (n - 1)) : 0.0;
    }
}

/* Pixels first .. first + P - 1 (global index b*H*W + y*W + x), counts[i] samples each:
 * mean (9, P) of emission, direct, indirect and var (3, P), the variance of the colour's mean,
 * each row `stride` >= P doubles after the one before (P: packed; a larger stride writes a column
 * range of a wider buffer). Every element is written.
 * nt > 1: OpenMP threads take runs of 16 pixels as they free up; nt = 1 never enters OpenMP (a
 * forked worker process stays safe, as in native.c). */
void torchgi_render_pixels(void *handle, const pt_render *R, long long first, const long long *counts, long long P,
                           long long stride, double *mean, double *var, int nt) {
    void *scene = ((pt_scene *)handle)->scene;
    if (nt > 1) {
#pragma omp parallel num_threads(nt)
        {
            float colour[3 * PT_BLOCK];
#pragma omp for schedule(dynamic, 1)
            for (long long run = 0; run < (P + 15) / 16; run++)
                film_pixels(R, scene, first, counts, stride, 16 * run, 16 * run + 16 < P ? 16 * run + 16 : P, mean,
                            var, colour);
        }
    } else {
        float colour[3 * PT_BLOCK];
        film_pixels(R, scene, first, counts, stride, 0, P, mean, var, colour);
    }
}

/* common.guides at pixel centres: out (11, P) = albedo 3, normal 3 (facing the camera), position 3,
 * depth (distance along the ray), hit (1.0 / 0.0); all 0 on a miss. Pixels 0 .. P-1 of one image. */
static void guide_pixels(const pt_render *R, void *scene, long long P, long long i0, long long i1, float *out) {
    profile_on(R);
    for (long long i = i0; i < i1; i++) {
        const float x = (float)(i % R->width) + 0.5f, y = (float)(i / R->width) + 0.5f;
        const float sx = (2.0f * R->tan_x / (float)R->width) * x - R->tan_x;
        const float sy = R->tan_y - (2.0f * R->tan_y / (float)R->height) * y;
        float d[3], t = 0.0f;
        for (int k = 0; k < 3; k++) d[k] = R->basis[k] * sx + R->basis[3 + k] * sy + R->basis[6 + k];
        const float inv = 1.0f / sqrtf(dot3(d, d));
        for (int k = 0; k < 3; k++) d[k] *= inv;
        const long long prim = trace(scene, R->origin, d, &t);
        for (int c = 0; c < 11; c++) out[c * P + i] = 0.0f;
        if (prim < 0) continue;
        float p[3];
        for (int k = 0; k < 3; k++) p[k] = R->origin[k] + d[k] * t;
        pt_vertex s;
        vertex(R, prim, p, d, &s);
        for (int k = 0; k < 3; k++) {
            out[k * P + i] = s.albedo[k];
            out[(3 + k) * P + i] = s.n[k];
            out[(6 + k) * P + i] = p[k];
        }
        out[9 * P + i] = t;
        out[10 * P + i] = 1.0f;
    }
}

void torchgi_render_guides(void *handle, const pt_render *R, long long P, float *out, int nt) {
    void *scene = ((pt_scene *)handle)->scene;
    if (nt > 1) {
#pragma omp parallel for num_threads(nt) schedule(dynamic, 1)
        for (long long run = 0; run < (P + 255) / 256; run++)
            guide_pixels(R, scene, P, 256 * run, 256 * run + 256 < P ? 256 * run + 256 : P, out);
    } else {
        guide_pixels(R, scene, P, 0, P, out);
    }
}
