"""Physical constants and Earth defaults, each with unit and source."""

EARTH_BOTTOM_RADIUS_M: float = 6_360_000.0
"""Planet radius [m]. Bruneton 2017 reference implementation (demo.cc, kBottomRadius)."""

EARTH_TOP_RADIUS_M: float = 6_420_000.0
"""Radius of the top of the atmosphere [m]. Bruneton 2017 (kTopRadius)."""

RAYLEIGH_COEFF_PER_M_UM4: float = 1.24062e-6
"""Rayleigh scattering at sea level is this times lambda[um]^-4 [1/m]. Bruneton 2017 (kRayleigh)."""

RAYLEIGH_SCALE_HEIGHT_M: float = 8000.0
"""Rayleigh density scale height [m]. Bruneton & Neyret 2008, Sec. 2.1; Bruneton 2017."""

MIE_SCALE_HEIGHT_M: float = 1200.0
"""Mie (aerosol) density scale height [m]. Bruneton & Neyret 2008, Sec. 2.1; Bruneton 2017."""

MIE_EXTINCTION_PER_M: float = 4.44e-6
"""Mie extinction at sea level [1/m]: Bruneton 2017's Angstrom beta 5.328e-3 / 1200 m."""

MIE_SINGLE_SCATTERING_ALBEDO: float = 0.9
"""Mie single-scattering albedo [1]. Bruneton 2017 (kMieSingleScatteringAlbedo)."""

MIE_G: float = 0.8
"""Cornette-Shanks asymmetry of the Mie phase function [1]. Bruneton 2017 (kMiePhaseFunctionG)."""

GROUND_ALBEDO: float = 0.1
"""Lambertian ground albedo [1]. Bruneton 2017 (kGroundAlbedo)."""

SUN_ANGULAR_RADIUS_RAD: float = 0.00935 / 2.0
"""Apparent solar angular radius [rad]. Bruneton 2017 (kSunAngularRadius)."""

DOBSON_UNIT_PER_M2: float = 2.687e20
"""Molecules per m^2 in one Dobson unit. Bruneton 2017 (kDobsonUnit)."""

LUMINOUS_EFFICACY_LM_PER_W: float = 683.0
"""Maximum luminous efficacy of photopic vision [lm/W] (CIE; CONTRACT.md)."""

PRESSURE_SCALE_HEIGHT_M: float = 8434.0
"""Scale height of surface pressure, R T / (M g) at 288.15 K (U.S. Standard Atmosphere 1976 sea-level
temperature, M = 0.0289644 kg/mol, g = 9.80665 m/s^2): a site at elevation z has p/p0 = exp(-z / 8434 m),
and its Rayleigh optical depth scales with p. [m]"""
