"""The synthetic scenes: for each, its volume, kind, varying parameters and camera set-up.

A scene varies only the parameters of its scenario (K of them); a static scene (K = 0) pins them to
``fixed``. Every scene lives in the box [-0.5, 0.5]^3 with its visible content inside the ball of
radius 0.5 (``fields.radial_window``); the cameras orbit at ``camera_distance`` with a 30 degree
horizontal field of view, which frames that ball with a margin.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from visnerf.scenes.fields import CosmicWebField, PlumeField, ShellsField, TangleField, VortexField
from visnerf.scenes.protocol import ParamAxis
from visnerf.scenes.reference_renderer import Box, DvrVolume, IsoVolume, Volume
from visnerf.scenes.transfer_function import (
    cosmic_tf,
    nested_shells_tf,
    plume_tf,
    shells_tf,
    translated_range_tf,
    two_range_tf,
)


@dataclass(frozen=True)
class SceneSpec:
    """Everything needed to generate one synthetic dataset."""

    name: str
    """Short snake_case identifier (the ``make-scene`` argument)."""
    title: str
    """Human title."""
    kind: Literal["dvr", "ir"]
    """Direct volume rendering or isosurface rendering."""
    build: Callable[..., Volume]
    """Volume from the varying parameter values followed by the ``fixed`` values."""
    axes: tuple[ParamAxis, ...] = ()
    """The varying parameters (K = len(axes)), in ``param_names`` order."""
    fixed: tuple[tuple[str, float], ...] = ()
    """Parameters pinned in this scene (name, value), passed to ``build`` after the varying ones."""
    description: str = ""
    """One line on what the scene shows."""
    step: float = 1.0 / 256.0
    """Ray-marching step of the reference renderer for this scene (world units), chosen per scene by
    convergence (see ``scene_catalog``)."""
    camera_distance: float = 2.1
    """Orbit radius of all cameras; 0.5 / sin(15 deg) = 1.93 frames the content ball exactly."""
    fov_x_deg: float = 30.0
    """Horizontal field of view (``camera_angle_x``)."""
    bbox: Box = ((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
    """Content box written to the dataset."""
    n_views: int = 42
    """Training views per parameter setting (``make-scene --views`` overrides it)."""
    resolution: int = 128
    """Image width and height in pixels (``make-scene --res`` overrides it)."""
    rgba: bool = False
    """Write RGBA images (straight alpha: the content's opacity) instead of RGB on white, as a
    volume renderer's saved frames often are; the loader composites them on the background."""

    @property
    def param_names(self) -> list[str]:
        return [axis.name for axis in self.axes]

    @property
    def fov_x_rad(self) -> float:
        return math.radians(self.fov_x_deg)

    def volume_at(self, params: tuple[float, ...]) -> Volume:
        """The volume at one setting of the varying parameters."""
        if len(params) != len(self.axes):
            raise ValueError(f"scene {self.name!r} takes {len(self.axes)} parameters, got {len(params)}")
        return self.build(*(float(p) for p in params), *(value for _, value in self.fixed))


def _plume(time: float) -> Volume:
    return DvrVolume(PlumeField(time), plume_tf(), support_radius=0.5)


def _tangle(isovalue: float) -> Volume:
    return IsoVolume(TangleField(), isovalue, support_radius=0.5)


def _vortex_tf1(opacity_low: float, opacity_high: float) -> Volume:
    return DvrVolume(VortexField(), two_range_tf(opacity_low, opacity_high), support_radius=0.5)


def _vortex_tf2(shift: float) -> Volume:
    return DvrVolume(VortexField(), translated_range_tf(shift), support_radius=0.5)


def _lit_plume(time: float) -> Volume:
    return DvrVolume(PlumeField(time), shells_tf(), support_radius=0.5, lit=True)


def _shells(time: float) -> Volume:
    return DvrVolume(ShellsField(time), nested_shells_tf(), support_radius=0.5, lit=True)


def _cosmo(omega_m: float, omega_b: float, hubble: float) -> Volume:
    return DvrVolume(CosmicWebField(omega_m, omega_b, hubble), cosmic_tf(), support_radius=0.5)


def scene_catalog() -> dict[str, SceneSpec]:
    """All scenes by name, varying scenes first, then their static versions."""
    time = ParamAxis("time", 0.0, 1.0, 5, "plumes grow, lean in and merge")
    series_time = ParamAxis("time", 0.0, 1.0, 30, "plumes grow, lean in and merge, seen as three lit shells")
    isovalue = ParamAxis("isovalue", 0.25, 0.85, 5, "blobs (high) -> branching frame -> holed shell (low)")
    opacity_low = ParamAxis("opacity_low", 0.02, 0.2, 3, "TF-1 opacity of the sheath range [0.15, 0.45]")
    opacity_high = ParamAxis("opacity_high", 0.1, 0.8, 3, "TF-1 opacity of the core range [0.6, 1.0]")
    tf_shift = ParamAxis(
        "tf_shift", 0.0, 1.0, 5, "TF-2: visible range moves from sheath (blue) to core (red)"
    )
    shells_time = ParamAxis("time", 0.0, 1.0, 30, "blobs rise, swirl, grow and flicker in a moving turbulent warp")
    omega_m = ParamAxis("omega_m", 0.12, 0.16, 3, "matter density: contrast of knots and filaments")
    omega_b = ParamAxis("omega_b", 0.0215, 0.0235, 3, "baryon density: smoothing of small scales")
    hubble = ParamAxis("hubble", 0.55, 0.85, 3, "Hubble constant: more small-scale structure")
    # Steps: images differ from step 1/768 by < 0.5 of an 8-bit level at the 99th percentile
    # (measured at 64x64: plume 0.08, cosmo 0.43 at 1/128; vortex TF-1 0.27, TF-2 0.28 at 1/256).
    # IR: the step only has to catch thin parts; bisection refines the hit.
    # Nested shells' peaks are 0.06 of the value wide, 1 to 4 pixels at 800x800: at 1/512 the images
    # differ from step 1/1536 by 1.0 to 1.3 levels at the 99th percentile (160x160).
    coarse, fine, thin = 1.0 / 128.0, 1.0 / 256.0, 1.0 / 512.0
    scenes = (
        SceneSpec("plume_time", "Merging plumes over time", "dvr", _plume, (time,),
                  description="three plumes rising, bending and merging; DVR", step=coarse),
        SceneSpec("tangle_iso", "Tangle isosurfaces", "ir", _tangle, (isovalue,),
                  description="nested and branching isosurfaces of the tangle cube; IR", step=coarse),
        SceneSpec("vortex_tf1", "Vortices, TF-1 (two opacities)", "dvr", _vortex_tf1,
                  (opacity_low, opacity_high), description="vortex ring and helix; opacities of two ranges",
                  step=fine),
        SceneSpec("vortex_tf2", "Vortices, TF-2 (moving range)", "dvr", _vortex_tf2, (tf_shift,),
                  description="vortex ring and helix; one visible range translated onto another", step=fine),
        SceneSpec("cosmo_sim", "Toy cosmology, three simulation parameters", "dvr", _cosmo,
                  (omega_m, omega_b, hubble), description="log-normal cosmic web; DVR", step=coarse),
        SceneSpec("lit_series", "Lit translucent shells over 30 timesteps", "dvr", _lit_plume, (series_time,),
                  description="three contour shells of the plumes, shaded with a headlight (highlights move "
                              "with the view); 20 views a timestep, as in situ series are kept",
                  step=fine, n_views=20),
        SceneSpec("shells_time", "Many small nested lit shells over 30 timesteps", "dvr", _shells, (shells_time,),
                  description="24 blobs of a turbulent moving field through three narrow transfer-function peaks "
                              "(translucent outer shells around opaque cores), headlight-lit with highlights; "
                              "RGBA 800x800, 20 views a timestep", step=thin, n_views=20, resolution=800, rgba=True),
        SceneSpec("plume_static", "Merging plumes (static)", "dvr", _plume, fixed=(("time", 0.5),),
                  description="plume_time at time 0.5", step=coarse),
        SceneSpec("tangle_static", "Tangle isosurface (static)", "ir", _tangle, fixed=(("isovalue", 0.5),),
                  description="tangle_iso at isovalue 0.5", step=coarse),
        SceneSpec("vortex_static", "Vortices (static)", "dvr", _vortex_tf1,
                  fixed=(("opacity_low", 0.08), ("opacity_high", 0.6)), description="vortex_tf1 at one TF",
                  step=fine),
        SceneSpec("cosmo_static", "Toy cosmology (static)", "dvr", _cosmo,
                  fixed=(("omega_m", 0.14), ("omega_b", 0.0225), ("hubble", 0.7)),
                  description="cosmo_sim at the centre of its ranges", step=coarse),
        SceneSpec("shells_static", "Many small nested lit shells (one timestep)", "dvr", _shells,
                  fixed=(("time", 0.5),), description="shells_time at time 0.5", step=thin, n_views=20,
                  resolution=800, rgba=True),
    )  # fmt: skip
    return {scene.name: scene for scene in scenes}


def get_scene(name: str) -> SceneSpec:
    """The scene called ``name``; a ``KeyError`` naming the known scenes otherwise."""
    catalog = scene_catalog()
    if name not in catalog:
        raise KeyError(f"unknown scene {name!r}; known scenes: {', '.join(catalog)}")
    return catalog[name]
