"""GLSL lookup functions for the ``--layout bruneton2017`` textures (written to ``atmosphere.glsl``).

The functions and their names follow Bruneton 2017's ``functions.glsl`` and the API of its
``kAtmosphereShader`` (GetSkyLuminance, GetSunAndSkyIlluminance, GetSolarLuminance), so a
renderer written for that API can include this file instead; they are written here for
skyfit's textures (docs/luts.md), and :mod:`skyfit.export.shader_reference` is their NumPy
transcription, line for line, which the tests and ``scripts/bruneton2017_accuracy.py`` run.
"""
from __future__ import annotations

from string import Template

TEMPLATE = Template(r"""#version 330
// Sky lookups for skyfit's `export-lut --layout bruneton2017` textures (docs/luts.md).
// Method: Bruneton & Neyret 2008, Sec. 4 and eq. 16 (sky radiance from precomputed tables);
// parametrisation and API: Bruneton 2017, "Precomputed Atmospheric Scattering: a New
// Implementation" (ebruneton/precomputed_atmospheric_scattering, functions.glsl, model.cc),
// with its current mu_s mapping. Written for these textures; NumPy transcription:
// skyfit/export/shader_reference.py.
//
// Units
//   lengths: km; positions relative to the planet's centre; directions unit vectors.
//   transmittance_texture  R, G, B: transmittance to the top at 680, 550, 440 nm [1].
//   scattering_texture     R, G, B: single Rayleigh (no phase function) + multiple scattering
//                          divided by RayleighPhaseFunction(nu); A: single Mie, red channel.
//                          Linear sRGB of the spectrum without the 683 lm/W factor [W/m^2 equivalent];
//                          x phase [1/sr] x SKY_SPECTRAL_RADIANCE_TO_LUMINANCE -> cd/m^2.
//   single_mie_scattering_texture  R, G, B, same units (used without COMBINED_SCATTERING_TEXTURES).
//   irradiance_texture     R, G, B: indirect irradiance of a horizontal surface, orders 1..N-1,
//                          same units; x SKY_SPECTRAL_RADIANCE_TO_LUMINANCE -> lux.
//   GetSkyLuminance, GetSolarLuminance: linear sRGB (D65) with Y = luminance [cd/m^2].
//   GetSunAndSkyIlluminance: [lux] (its sun term from SOLAR_IRRADIANCE and the transmittance
//   at the three wavelengths, as 2017).
// Textures: linear filtering, CLAMP_TO_EDGE; the scattering images are 3-D textures of width
// NU * MU_S, height MU and depth R, stored as R slices stacked vertically (row = i_r MU + i_mu).
// Orders of scattering in the tables: $orders.

#define COMBINED_SCATTERING_TEXTURES  // remove to read single Mie from single_mie_scattering_texture
#define MIE_HENYEY_GREENSTEIN $hg     // 1: Henyey-Greenstein, 0: Cornette-Shanks (2017's)

$sizes
const float BOTTOM_RADIUS = $bottom;  // km
const float TOP_RADIUS = $top;  // km
const float MU_S_MIN = $mu_s_min;  // lowest sun zenith cosine in the scattering texture
const float SUN_ANGULAR_RADIUS = $sun_radius;  // rad
const float MIE_G = $mie_g;
const vec3 SOLAR_IRRADIANCE = $solar;  // W/(m^2 nm) at 680, 550, 440 nm
const vec3 RAYLEIGH_SCATTERING = $rayleigh;  // sea level, 1/km, at 680, 550, 440 nm
const vec3 MIE_SCATTERING = $mie;  // sea level, 1/km, at 680, 550, 440 nm
const vec3 GROUND_ALBEDO = $albedo;  // at 680, 550, 440 nm
const vec3 SKY_SPECTRAL_RADIANCE_TO_LUMINANCE = $sky_k;  // lm/W
const vec3 SUN_SPECTRAL_RADIANCE_TO_LUMINANCE = $sun_k;  // lm/W per W/(m^2 nm) at 680, 550, 440 nm
const float PI = 3.14159265358979323846;

uniform sampler2D transmittance_texture;
uniform sampler3D scattering_texture;
uniform sampler3D single_mie_scattering_texture;
uniform sampler2D irradiance_texture;

float ClampCosine(float mu) { return clamp(mu, -1.0, 1.0); }
float ClampRadius(float r) { return clamp(r, BOTTOM_RADIUS, TOP_RADIUS); }
float SafeSqrt(float a) { return sqrt(max(a, 0.0)); }

float DistanceToTopAtmosphereBoundary(float r, float mu) {
  return max(-r * mu + SafeSqrt(r * r * (mu * mu - 1.0) + TOP_RADIUS * TOP_RADIUS), 0.0);
}

float DistanceToBottomAtmosphereBoundary(float r, float mu) {
  return max(-r * mu - SafeSqrt(r * r * (mu * mu - 1.0) + BOTTOM_RADIUS * BOTTOM_RADIUS), 0.0);
}

bool RayIntersectsGround(float r, float mu) {
  return mu < 0.0 && r * r * (mu * mu - 1.0) + BOTTOM_RADIUS * BOTTOM_RADIUS >= 0.0;
}

// x in [0, 1] onto the texel centres of a texture of n texels.
float GetTextureCoordFromUnitRange(float x, int n) {
  return 0.5 / float(n) + x * (1.0 - 1.0 / float(n));
}

vec2 GetTransmittanceTextureUvFromRMu(float r, float mu) {
  float H = sqrt(TOP_RADIUS * TOP_RADIUS - BOTTOM_RADIUS * BOTTOM_RADIUS);
  float rho = SafeSqrt(r * r - BOTTOM_RADIUS * BOTTOM_RADIUS);
  float d = DistanceToTopAtmosphereBoundary(r, mu);
  float d_min = TOP_RADIUS - r;
  float d_max = rho + H;
  return vec2(GetTextureCoordFromUnitRange((d - d_min) / (d_max - d_min), TRANSMITTANCE_TEXTURE_WIDTH),
              GetTextureCoordFromUnitRange(rho / H, TRANSMITTANCE_TEXTURE_HEIGHT));
}

vec3 GetTransmittanceToTopAtmosphereBoundary(float r, float mu) {
  return texture(transmittance_texture, GetTransmittanceTextureUvFromRMu(r, mu)).rgb;
}

// Transmittance between the point (r, mu) and the point at distance d along the ray.
vec3 GetTransmittance(float r, float mu, float d, bool ray_r_mu_intersects_ground) {
  float r_d = ClampRadius(sqrt(d * d + 2.0 * r * mu * d + r * r));
  float mu_d = ClampCosine((r * mu + d) / r_d);
  if (ray_r_mu_intersects_ground) {
    return min(GetTransmittanceToTopAtmosphereBoundary(r_d, -mu_d) /
               GetTransmittanceToTopAtmosphereBoundary(r, -mu), vec3(1.0));
  }
  return min(GetTransmittanceToTopAtmosphereBoundary(r, mu) /
             GetTransmittanceToTopAtmosphereBoundary(r_d, mu_d), vec3(1.0));
}

// Transmittance to the sun times the fraction of its disc above the horizon.
vec3 GetTransmittanceToSun(float r, float mu_s) {
  float sin_theta_h = BOTTOM_RADIUS / r;
  float cos_theta_h = -sqrt(max(1.0 - sin_theta_h * sin_theta_h, 0.0));
  return GetTransmittanceToTopAtmosphereBoundary(r, mu_s) *
      smoothstep(-sin_theta_h * SUN_ANGULAR_RADIUS, sin_theta_h * SUN_ANGULAR_RADIUS, mu_s - cos_theta_h);
}

float RayleighPhaseFunction(float nu) {
  return 3.0 / (16.0 * PI) * (1.0 + nu * nu);  // [1/sr]
}

float MiePhaseFunction(float g, float nu) {
#if MIE_HENYEY_GREENSTEIN
  return (1.0 - g * g) / (4.0 * PI * pow(1.0 + g * g - 2.0 * g * nu, 1.5));
#else
  float k = 3.0 / (8.0 * PI) * (1.0 - g * g) / (2.0 + g * g);
  return k * (1.0 + nu * nu) / pow(1.0 + g * g - 2.0 * g * nu, 1.5);
#endif
}

vec4 GetScatteringTextureUvwzFromRMuMuSNu(float r, float mu, float mu_s, float nu,
                                          bool ray_r_mu_intersects_ground) {
  float H = sqrt(TOP_RADIUS * TOP_RADIUS - BOTTOM_RADIUS * BOTTOM_RADIUS);
  float rho = SafeSqrt(r * r - BOTTOM_RADIUS * BOTTOM_RADIUS);
  float u_r = GetTextureCoordFromUnitRange(rho / H, SCATTERING_TEXTURE_R_SIZE);
  float r_mu = r * mu;
  float discriminant = r_mu * r_mu - r * r + BOTTOM_RADIUS * BOTTOM_RADIUS;
  float u_mu;
  if (ray_r_mu_intersects_ground) {  // lower half: distance to the ground
    float d = -r_mu - SafeSqrt(discriminant);
    float d_min = r - BOTTOM_RADIUS;
    float d_max = rho;
    u_mu = 0.5 - 0.5 * GetTextureCoordFromUnitRange(
        d_max == d_min ? 0.0 : (d - d_min) / (d_max - d_min), SCATTERING_TEXTURE_MU_SIZE / 2);
  } else {  // upper half: distance to the top
    float d = -r_mu + SafeSqrt(discriminant + H * H);
    float d_min = TOP_RADIUS - r;
    float d_max = rho + H;
    u_mu = 0.5 + 0.5 * GetTextureCoordFromUnitRange(
        (d - d_min) / (d_max - d_min), SCATTERING_TEXTURE_MU_SIZE / 2);
  }
  float d = DistanceToTopAtmosphereBoundary(BOTTOM_RADIUS, mu_s);
  float d_min = TOP_RADIUS - BOTTOM_RADIUS;
  float d_max = H;
  float a = (d - d_min) / (d_max - d_min);
  float D = DistanceToTopAtmosphereBoundary(BOTTOM_RADIUS, MU_S_MIN);
  float A = (D - d_min) / (d_max - d_min);
  float u_mu_s = GetTextureCoordFromUnitRange(max(1.0 - a / A, 0.0) / (1.0 + a), SCATTERING_TEXTURE_MU_S_SIZE);
  float u_nu = (nu + 1.0) / 2.0;
  return vec4(u_nu, u_mu_s, u_mu, u_r);
}

// Single Mie from the combined texture's alpha (2017's approximation: the Mie/Rayleigh
// colour ratio of the scattering coefficients).
vec3 GetExtrapolatedSingleMieScattering(vec4 scattering) {
  if (scattering.r <= 0.0) {
    return vec3(0.0);
  }
  return scattering.rgb * scattering.a / scattering.r *
      (RAYLEIGH_SCATTERING.r / MIE_SCATTERING.r) * (MIE_SCATTERING / RAYLEIGH_SCATTERING);
}

vec3 GetCombinedScattering(float r, float mu, float mu_s, float nu, bool ray_r_mu_intersects_ground,
                           out vec3 single_mie_scattering) {
  vec4 uvwz = GetScatteringTextureUvwzFromRMuMuSNu(r, mu, mu_s, nu, ray_r_mu_intersects_ground);
  float tex_coord_x = uvwz.x * float(SCATTERING_TEXTURE_NU_SIZE - 1);
  float tex_x = floor(tex_coord_x);
  float lerp = tex_coord_x - tex_x;
  vec3 uvw0 = vec3((tex_x + uvwz.y) / float(SCATTERING_TEXTURE_NU_SIZE), uvwz.z, uvwz.w);
  vec3 uvw1 = vec3((tex_x + 1.0 + uvwz.y) / float(SCATTERING_TEXTURE_NU_SIZE), uvwz.z, uvwz.w);
  vec4 combined = texture(scattering_texture, uvw0) * (1.0 - lerp) + texture(scattering_texture, uvw1) * lerp;
#ifdef COMBINED_SCATTERING_TEXTURES
  single_mie_scattering = GetExtrapolatedSingleMieScattering(combined);
#else
  single_mie_scattering = texture(single_mie_scattering_texture, uvw0).rgb * (1.0 - lerp) +
      texture(single_mie_scattering_texture, uvw1).rgb * lerp;
#endif
  return combined.rgb;
}

vec2 GetIrradianceTextureUvFromRMuS(float r, float mu_s) {
  float x_r = (r - BOTTOM_RADIUS) / (TOP_RADIUS - BOTTOM_RADIUS);
  float x_mu_s = mu_s * 0.5 + 0.5;
  return vec2(GetTextureCoordFromUnitRange(x_mu_s, IRRADIANCE_TEXTURE_WIDTH),
              GetTextureCoordFromUnitRange(x_r, IRRADIANCE_TEXTURE_HEIGHT));
}

vec3 GetIrradiance(float r, float mu_s) {
  return texture(irradiance_texture, GetIrradianceTextureUvFromRMuS(r, mu_s)).rgb;
}

// Sky luminance seen from `camera` (km, from the planet's centre) along `view_ray`, without the
// sun's disc and without the ground's own light [cd/m^2]; `transmittance` to the top (0 when the
// ray hits the ground). An observer in space is first moved to the top of the atmosphere.
vec3 GetSkyLuminance(vec3 camera, vec3 view_ray, vec3 sun_direction, out vec3 transmittance) {
  float r = length(camera);
  float rmu = dot(camera, view_ray);
  float distance_to_top_atmosphere_boundary = -rmu - sqrt(rmu * rmu - r * r + TOP_RADIUS * TOP_RADIUS);
  if (distance_to_top_atmosphere_boundary > 0.0) {
    camera = camera + view_ray * distance_to_top_atmosphere_boundary;
    r = TOP_RADIUS;
    rmu += distance_to_top_atmosphere_boundary;
  } else if (r > TOP_RADIUS) {
    transmittance = vec3(1.0);
    return vec3(0.0);
  }
  float mu = rmu / r;
  float mu_s = dot(camera, sun_direction) / r;
  float nu = dot(view_ray, sun_direction);
  bool ray_r_mu_intersects_ground = RayIntersectsGround(r, mu);
  transmittance = ray_r_mu_intersects_ground ? vec3(0.0) : GetTransmittanceToTopAtmosphereBoundary(r, mu);
  vec3 single_mie_scattering;
  vec3 scattering = GetCombinedScattering(r, mu, mu_s, nu, ray_r_mu_intersects_ground, single_mie_scattering);
  return (scattering * RayleighPhaseFunction(nu) + single_mie_scattering * MiePhaseFunction(MIE_G, nu)) *
      SKY_SPECTRAL_RADIANCE_TO_LUMINANCE;
}

// Sun and sky illuminance of a surface at p (km, from the centre) with the given normal [lux].
vec3 GetSunAndSkyIlluminance(vec3 p, vec3 normal, vec3 sun_direction, out vec3 sky_illuminance) {
  float r = length(p);
  float mu_s = dot(p, sun_direction) / r;
  sky_illuminance = GetIrradiance(r, mu_s) * (1.0 + dot(normal, p) / r) * 0.5 * SKY_SPECTRAL_RADIANCE_TO_LUMINANCE;
  return SOLAR_IRRADIANCE * GetTransmittanceToSun(r, mu_s) * max(dot(normal, sun_direction), 0.0) *
      SUN_SPECTRAL_RADIANCE_TO_LUMINANCE;
}

// The sky plus, for rays that hit the ground, the Lambertian ground (GROUND_ALBEDO) lit by the sun
// and the sky, attenuated to the camera (2017 demo.glsl's ground with a horizontal surface) [cd/m^2].
vec3 GetSkyAndGroundLuminance(vec3 camera, vec3 view_ray, vec3 sun_direction) {
  vec3 transmittance;
  vec3 sky = GetSkyLuminance(camera, view_ray, sun_direction, transmittance);
  float r = length(camera);
  float mu = dot(camera, view_ray) / r;
  if (r > TOP_RADIUS || !RayIntersectsGround(r, mu)) {
    return sky;
  }
  float d = DistanceToBottomAtmosphereBoundary(r, mu);
  vec3 p = camera + view_ray * d;
  vec3 normal = normalize(p);
  vec3 sky_illuminance;
  vec3 sun_illuminance = GetSunAndSkyIlluminance(BOTTOM_RADIUS * normal, normal, sun_direction, sky_illuminance);
  vec3 ground = GROUND_ALBEDO / PI * (sun_illuminance + sky_illuminance);
  return sky + GetTransmittance(r, mu, d, true) * ground;
}

vec3 GetSolarLuminance() {  // the sun's disc, outside the atmosphere [cd/m^2]
  return SOLAR_IRRADIANCE / (PI * SUN_ANGULAR_RADIUS * SUN_ANGULAR_RADIUS) * SUN_SPECTRAL_RADIANCE_TO_LUMINANCE;
}
""")
