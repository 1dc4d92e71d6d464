"""Analytic scalar fields for the synthetic scenes: smooth, cheap, defined everywhere.

Every field is a frozen dataclass holding only the parameters its scenario needs and is called on
world points ``[n, 3]`` (any float dtype, any device) to give values ``[n]`` in the same dtype. The
scene fields are multiplied by ``radial_window`` so that they vanish outside a ball of radius 0.5
around the origin (``SUPPORT_RADIUS``): everything visible lies inside the box [-0.5, 0.5]^3 and a
renderer may clip its rays to that ball. World +y is up. The closed-form fields at the end of the
module (constant, radial distance, linear ramp) serve the renderer's tests.

All fields are differentiable in the points (plain torch operations), but renderers here take
normals by central differences, so a kink (the axis of the vortex ring) never yields NaN.
"""

import math
from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor


def smoothstep(edge0: float, edge1: float, x: Float[Tensor, "*shape"]) -> Float[Tensor, "*shape"]:
    """C1 Hermite step: 0 below ``edge0``, 1 above ``edge1`` (``edge0 < edge1``)."""
    s = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def radial_window(
    points: Float[Tensor, "n 3"], inner: float = 0.42, outer: float = 0.5
) -> Float[Tensor, " n"]:
    """1 inside radius ``inner``, 0 outside radius ``outer``, C1 in between."""
    radius = torch.linalg.norm(points, dim=-1)  # [n]
    return 1.0 - smoothstep(inner, outer, radius)


@dataclass(frozen=True)
class PlumeField:
    """Three buoyant plumes rising from the floor y = -0.4; with time they grow, lean in and merge.

    Values lie in [0, 1): ``1 - exp(-gain * sum of plume densities)``.
    """

    time: float
    """Normalised time in [0, 1]: plume height 0.3 -> 0.85, lean towards the axis 0.15 -> 1."""
    gain: float = 1.6
    """Saturation gain of the summed densities."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        x, y, z = points.unbind(-1)
        height = 0.3 + 0.55 * self.time
        lean = 0.15 + 0.85 * self.time
        s = (y + 0.4).clamp_min(0.0)  # [n] height above the floor
        u = (s / 0.85).clamp(max=1.0)  # [n] normalised height
        pull = 1.0 - lean * u * u  # [n] fraction of the source offset kept at this height
        radius = 0.035 + 0.1 * s  # [n] the plumes widen as they rise
        cap = torch.sigmoid((height - s) / 0.03) * smoothstep(0.0, 0.04, s)  # [n] soft bottom and top
        total = torch.zeros_like(x)
        for k in range(3):
            angle = 2.0 * math.pi * k / 3.0 + 0.5 * math.pi
            phase = 2.1 * k + 5.0 * self.time
            cx = 0.2 * math.cos(angle) * pull + 0.03 * torch.sin(11.0 * s + phase)  # [n]
            cz = 0.2 * math.sin(angle) * pull + 0.03 * torch.cos(9.0 * s + 1.3 * phase)  # [n]
            d2 = (x - cx).square() + (z - cz).square()  # [n]
            puffs = 0.85 + 0.15 * torch.sin(25.0 * s - 8.0 * self.time + phase)  # [n] eddies along the rise
            total = total + torch.exp(-0.5 * d2 / radius.square()) * (1.0 - 0.45 * u) * puffs
        return -torch.expm1(-self.gain * total * cap) * radial_window(points)


@dataclass(frozen=True)
class TangleField:
    """The tangle cube ``sum(q^4 - 5 q^2)`` with ``q = scale * p``, negated and normalised.

    ``v = -sum_i (q_i^4 - 5 q_i^2) / 18.75``: 1 at the eight blob centres (q_i = +-sqrt(2.5)), 0 at
    the origin (a local minimum, so isovalues in (0, 1/3) give a surface nested around it), 2/3 at the
    edge saddles and 1/3 at the face saddles: the isosurfaces are eight blobs above 2/3, a branching
    frame between 1/3 and 2/3, and a holed shell with an inner sphere below 1/3.
    """

    scale: float = 8.0
    """World-to-tangle scale: blob centres at +-sqrt(2.5) / scale on each axis."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        q2 = (self.scale * points).square()  # [n, 3]
        raw = (q2.square() - 5.0 * q2).sum(dim=-1)  # [n]
        return (-raw / 18.75) * radial_window(points)


@dataclass(frozen=True)
class VortexField:
    """Vorticity magnitude of a vortex ring above a helical vortex tube (Lamb-Oseen core profiles).

    Each vortex contributes ``exp(-(d / core)^2)`` at distance d from its centre line; the two
    combine as ``1 - (1 - a)(1 - b)``, so values lie in [0, 1]: near 1 in the cores, low in the
    sheaths around them.
    """

    ring_radius: float = 0.24
    """Radius of the vortex ring (horizontal, centred on the y axis at y = ring_height)."""
    ring_height: float = 0.14
    """Height of the ring's plane."""
    ring_core: float = 0.075
    """Core radius of the ring."""
    helix_radius: float = 0.12
    """Radius of the helix around the y axis."""
    helix_turns_per_unit: float = 1.6
    """Turns of the helix per unit of height."""
    helix_core: float = 0.06
    """Core radius of the helical tube."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        x, y, z = points.unbind(-1)
        rho = torch.sqrt(x.square() + z.square() + 1e-12)  # [n] distance to the y axis
        d2_ring = (rho - self.ring_radius).square() + (y - self.ring_height).square()  # [n]
        ring = torch.exp(-d2_ring / self.ring_core**2)  # [n]
        theta = 2.0 * math.pi * self.helix_turns_per_unit * y  # [n]
        hx = self.helix_radius * torch.cos(theta)  # [n] helix centre line at this height
        hz = self.helix_radius * torch.sin(theta)
        d2_helix = (x - hx).square() + (z - hz).square()  # [n] in-plane distance (steep helix)
        along = smoothstep(-0.42, -0.3, y) * (1.0 - smoothstep(0.0, 0.12, y))  # [n] helix extent
        helix = torch.exp(-d2_helix / self.helix_core**2) * along  # [n]
        return (1.0 - (1.0 - ring) * (1.0 - helix)) * radial_window(points)


@dataclass(frozen=True)
class CosmicWebField:
    """A toy cosmological density: a log-normal transform of a fixed-phase Gaussian random field.

    The same "universe" (wave vectors and phases drawn once from ``seed``) is evolved under three
    simulation-like parameters: ``omega_m`` sets the growth (contrast of knots and filaments against
    voids), ``hubble`` the spectrum's shape (turnover k ~ omega_m * hubble: more small-scale power
    as it rises) and ``omega_b`` the gas smoothing (scale ~ omega_b / omega_m: smoother as it rises).
    Values lie in (0, 1): a sigmoid of the log density.
    """

    omega_m: float
    """Matter density, about 0.12 - 0.16."""
    omega_b: float
    """Baryon density, about 0.0215 - 0.0235."""
    hubble: float
    """Dimensionless Hubble constant, about 0.55 - 0.85."""
    n_modes: int = 20
    """Number of plane waves in the random field."""
    seed: int = 7
    """Seed of the wave vectors and phases."""
    block_points: int = 16384
    """Points evaluated together (a speed setting only)."""

    def modes(self, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """Wave vectors ``[3, n_modes]``, phases ``[n_modes]`` and amplitudes ``[n_modes]``."""
        gen = torch.Generator().manual_seed(self.seed)
        direction = torch.randn(3, self.n_modes, generator=gen, dtype=torch.float64)
        direction = direction / torch.linalg.norm(direction, dim=0, keepdim=True)  # [3, m]
        k = 2.0 * math.pi * torch.logspace(0.2, 1.0, self.n_modes, dtype=torch.float64)  # [m] 1.6 .. 10
        phases = 2.0 * math.pi * torch.rand(self.n_modes, generator=gen, dtype=torch.float64)  # [m]
        k_turn = 2.0 * math.pi * 40.0 * self.omega_m * self.hubble  # turnover, ~ 2 pi * 4
        smoothing = 0.14 * self.omega_b / self.omega_m  # gas smoothing length, ~ 0.02
        power = k / (1.0 + (k / k_turn) ** 4) * torch.exp(-((k * smoothing) ** 2))  # [m], k^3 P(k)
        amplitude = torch.sqrt(power)  # [m]
        amplitude = amplitude * math.sqrt(2.0) / torch.linalg.norm(amplitude)  # unit variance
        wave = direction * k  # [3, m]
        return (
            wave.to(dtype=dtype, device=device),
            phases.to(dtype=dtype, device=device),
            amplitude.to(dtype=dtype, device=device),
        )

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        wave, phases, amplitude = self.modes(points.dtype, points.device)
        delta = torch.empty_like(points[:, 0])  # [n], unit variance
        for start in range(0, points.shape[0], self.block_points):  # keeps [block, n_modes] in cache
            block = slice(start, start + self.block_points)
            delta[block] = torch.cos(torch.addmm(phases, points[block], wave)) @ amplitude
        growth = 1.4 * (self.omega_m / 0.14) ** 2  # log-normal contrast
        log_density = growth * delta - 0.5 * growth**2  # [n]
        return torch.sigmoid(1.5 * (log_density - 0.6)) * radial_window(points)


@dataclass(frozen=True)
class ShellsField:
    """Many small buoyant blobs in a turbulent flow: a combustion or mantle-like field whose narrow
    transfer-function peaks draw nested thin shells around every blob.

    ``n_blobs`` Gaussian blobs (radii 0.03 to 0.065) rise and swirl about the vertical axis while
    they grow and fade; the space they are sampled in is displaced by ``n_modes`` plane waves
    whose phases travel with time (a moving turbulent warp), so their shells wrinkle and the
    wrinkles move. Values lie in [0, 1): ``1 - exp(-sum of blob densities)``.
    """

    time: float
    """Normalised time in [0, 1]."""
    n_blobs: int = 24
    """Number of blobs."""
    n_modes: int = 8
    """Plane waves of the turbulent displacement."""
    warp: float = 0.03
    """Largest displacement (world units): the waves' amplitudes add up to it."""
    seed: int = 11
    """Seed of the blobs' paths and the waves."""
    block_points: int = 16384
    """Points evaluated together (a speed setting only)."""

    def blobs(self, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """Centres ``[b, 3]``, inverse squared radii ``[b]`` and peak heights ``[b]`` at ``time``."""
        gen = torch.Generator().manual_seed(self.seed)
        b, t = self.n_blobs, self.time
        radius0 = 0.03 + 0.035 * torch.rand(b, generator=gen, dtype=torch.float64)  # [b]
        ring = 0.04 + 0.3 * torch.rand(b, generator=gen, dtype=torch.float64)  # distance to the axis
        angle0 = 2.0 * math.pi * torch.rand(b, generator=gen, dtype=torch.float64)
        height0 = -0.32 + 0.5 * torch.rand(b, generator=gen, dtype=torch.float64)
        rise = 0.1 + 0.15 * torch.rand(b, generator=gen, dtype=torch.float64)
        spin = (0.6 + 0.9 * torch.rand(b, generator=gen, dtype=torch.float64)) * torch.where(
            torch.rand(b, generator=gen, dtype=torch.float64) < 0.5, -1.0, 1.0
        )
        phase = 2.0 * math.pi * torch.rand(b, generator=gen, dtype=torch.float64)
        angle = angle0 + spin * t  # [b] swirl about the vertical axis
        rho = ring * (1.0 + 0.25 * torch.sin(3.0 * t + phase))  # [b] breathing in and out
        centres = torch.stack(
            [rho * torch.cos(angle), height0 + rise * t, rho * torch.sin(angle)], dim=-1
        )  # [b, 3]
        radius = radius0 * (0.8 + 0.35 * t + 0.1 * torch.sin(4.0 * t + phase))  # [b] grow as they rise
        height = 1.3 + 0.5 * torch.sin(2.5 * t + 2.0 * phase)  # [b] flicker: shells appear and vanish
        return (
            centres.to(dtype=dtype, device=device),
            (1.0 / radius.square()).to(dtype=dtype, device=device),
            height.to(dtype=dtype, device=device),
        )

    def waves(self, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor]:
        """Wave vectors ``[3, m]``, phases at ``time`` ``[m]`` and displacements ``[m, 3]``."""
        gen = torch.Generator().manual_seed(self.seed + 1)
        m = self.n_modes
        direction = torch.randn(3, m, generator=gen, dtype=torch.float64)
        direction = direction / torch.linalg.norm(direction, dim=0, keepdim=True)  # [3, m]
        k = 2.0 * math.pi * torch.linspace(2.0, 6.0, m, dtype=torch.float64)  # [m] wavelengths 0.5 .. 0.17
        speed = 1.0 + 2.0 * torch.rand(m, generator=gen, dtype=torch.float64)
        phase = 2.0 * math.pi * torch.rand(m, generator=gen, dtype=torch.float64) + 2.0 * math.pi * speed * self.time
        across = torch.linalg.cross(direction.T, torch.randn(m, 3, generator=gen, dtype=torch.float64))  # [m, 3]
        across = across / torch.linalg.norm(across, dim=-1, keepdim=True)  # transverse: no compression
        amplitude = k[0] / k  # [m] finer waves displace less
        amplitude = self.warp * amplitude / amplitude.sum()  # no point moves farther than ``warp``
        return (
            (direction * k).to(dtype=dtype, device=device),
            phase.to(dtype=dtype, device=device),
            (across * amplitude[:, None]).to(dtype=dtype, device=device),
        )

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        centres, inv_r2, height = self.blobs(points.dtype, points.device)
        wave, phase, displacement = self.waves(points.dtype, points.device)
        total = torch.empty_like(points[:, 0])  # [n]
        for start in range(0, points.shape[0], self.block_points):  # keeps [block, b] in cache
            block = points[start : start + self.block_points]
            warped = block + torch.sin(torch.addmm(phase, block, wave)) @ displacement  # [block, 3]
            d2 = (warped[:, None, :] - centres).square().sum(-1)  # [block, b]
            total[start : start + self.block_points] = torch.exp(-0.5 * d2 * inv_r2) @ height
        return -torch.expm1(-total) * radial_window(points)


@dataclass(frozen=True)
class ConstantField:
    """The same value everywhere (a homogeneous medium once clipped to a box)."""

    value: float = 1.0
    """The field's value."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        return torch.full_like(points[:, 0], self.value)


@dataclass(frozen=True)
class RadialDistanceField:
    """Distance to ``centre``: its isosurface at r is the sphere of radius r."""

    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Centre of the spheres."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        centre = torch.tensor(self.centre, dtype=points.dtype, device=points.device)
        return torch.linalg.norm(points - centre, dim=-1)


@dataclass(frozen=True)
class LinearRampField:
    """``offset + dot(gradient, p)``: a ramp whose integral along any line has a closed form."""

    gradient: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Gradient of the ramp."""
    offset: float = 0.5
    """Value at the origin."""

    def __call__(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        gradient = torch.tensor(self.gradient, dtype=points.dtype, device=points.device)
        return points @ gradient + self.offset
