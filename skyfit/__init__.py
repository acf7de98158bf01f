"""skyfit: fit a physically based atmosphere to measured skies.

The Python API (:mod:`skyfit.api`; README "Python API")::

    atm = skyfit.load_atmosphere("earth")
    sky = skyfit.render(atm, skyfit.FisheyeCamera(64), sun=(60, 135))
    result = skyfit.fit(skyfit.Observation.from_arrays(sky.rgb, camera, sun=(60, 135)), "earth")

Layers, lowest first (docs/architecture.md): geometry -> atmosphere -> transmittance ->
scattering -> render -> camera -> io -> fit -> export -> api -> tools -> cli.
"""
__version__ = "0.1.0"

from .api import (  # noqa: E402  (after __version__, which modules below read)
    ACCURATE,
    FitResult,
    PhotoResult,
    Sky,
    envmap,
    export_luts,
    fit,
    fit_photo,
    load_atmosphere,
    load_result,
    render,
    resolve_device,
    sample,
    sun_vector,
)
from .atmosphere import Atmosphere  # noqa: E402
from .batch import batch  # noqa: E402
from .camera import FisheyeCamera, sun_position  # noqa: E402
from .fit import Observation  # noqa: E402

__all__ = [
    "ACCURATE",
    "Atmosphere",
    "FisheyeCamera",
    "FitResult",
    "Observation",
    "PhotoResult",
    "Sky",
    "__version__",
    "batch",
    "envmap",
    "export_luts",
    "fit",
    "fit_photo",
    "load_atmosphere",
    "load_result",
    "render",
    "resolve_device",
    "sample",
    "sun_position",
    "sun_vector",
]


def _callable_package(name: str, function):
    """Make the subpackage ``skyfit.<name>`` callable as ``function``.

    ``skyfit.render(...)`` and ``skyfit.fit(...)`` are the API's verbs, and ``skyfit.render`` /
    ``skyfit.fit`` are also subpackages (``skyfit.render.colour``, ``import skyfit.fit.sample``).
    A function bound to the package's name would hide the subpackage from ``import a.b.c as d``
    and from attribute access; a module whose class has ``__call__`` serves both. No library
    offers this, hence the few lines here.
    """
    import sys
    import types

    module = sys.modules[f"{__name__}.{name}"]
    module.__class__ = type(f"_Callable_{name}", (types.ModuleType,),
                            {"__call__": staticmethod(function), "__wrapped__": function})
    return module


render = _callable_package("render", render)  # noqa: F811  (the subpackage, callable as the API function)
fit = _callable_package("fit", fit)  # noqa: F811
batch = _callable_package("batch", batch)  # noqa: F811  (the module skyfit.batch, callable as skyfit.batch(...))
