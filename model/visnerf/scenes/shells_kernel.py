"""The reference renderer's DVR march for ``ShellsField`` as one compiled loop a ray (CPU, numba).

The nested-shells scene is drawn at 800x800 with narrow transfer-function peaks, which need a
step of 1/512: the vectorised march (``reference_renderer._render_dvr``, this loop's slow twin)
would take about two minutes an image, this loop about ten seconds. It computes the same samples
(segment midpoints of the same uniform segments, the same transfer function, the same headlight
shading, the gradient in closed form where the twin takes central differences) in float64, and
skips every sample in a cell where no value can reach the transfer function's first peak
(``cell_tables``: a bound on the blobs' sum over the cell, warp included), where the extinction is
zero and the sample adds nothing. Tested against the twin.
"""

import math
from typing import no_type_check

import numpy as np
import torch
from jaxtyping import Float, UInt8
from torch import Tensor

from visnerf.compiled import jit, serves
from visnerf.data.cameras import Intrinsics, image_rays
from visnerf.scenes.fields import ShellsField
from visnerf.scenes.raymarch import ray_intervals, uniform_segments
from visnerf.scenes.reference_renderer import DvrVolume, MarchConfig, RayOutput, Volume, render_image
from visnerf.scenes.transfer_function import TransferFunction

FAR_EXPONENT = 14.0
"""A cell's blob list leaves out the blobs whose exponent exceeds this everywhere in the cell: each
adds less than ``exp(-14) = 8e-7`` of its height there (the twin's values differ by less than
1e-5, a thousandth of an 8-bit level's worth of opacity)."""


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _warp(x, y, z, wave, phase, disp):  # numba
    """The point moved by the field's turbulent displacement (``ShellsField.waves``)."""
    wx, wy, wz = x, y, z
    for k in range(phase.shape[0]):
        s = math.sin(x * wave[0, k] + y * wave[1, k] + z * wave[2, k] + phase[k])
        wx += s * disp[k, 0]
        wy += s * disp[k, 1]
        wz += s * disp[k, 2]
    return wx, wy, wz


_warp_inline = jit(_warp, inline=True)


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _value(x, y, z, centres, inv_r2, height, wave, phase, disp, blobs, n_near):  # numba
    wx, wy, wz = _warp_inline(x, y, z, wave, phase, disp)
    total = 0.0
    for j in range(n_near):
        i = blobs[j]
        dx, dy, dz = wx - centres[i, 0], wy - centres[i, 1], wz - centres[i, 2]
        total += height[i] * math.exp(-0.5 * (dx * dx + dy * dy + dz * dz) * inv_r2[i])
    edge = min(max((math.sqrt(x * x + y * y + z * z) - 0.42) / 0.08, 0.0), 1.0)  # radial_window
    return -math.expm1(-total) * (1.0 - edge * edge * (3.0 - 2.0 * edge))


_value_inline = jit(_value, inline=True)


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _facing(px, py, pz, dx, dy, dz, centres, inv_r2, height, wave, phase, disp, blobs, n_near):
    """|cos| of the field's gradient (in closed form: the warp's Jacobian carries the blobs' gradient
    back to the point) with the ray; 1 where the gradient vanishes."""
    wx, wy, wz = _warp_inline(px, py, pz, wave, phase, disp)
    total = gx = gy = gz = 0.0  # the blobs' sum and its gradient in the warped point
    for j in range(n_near):
        i = blobs[j]
        ex, ey, ez = wx - centres[i, 0], wy - centres[i, 1], wz - centres[i, 2]
        term = height[i] * math.exp(-0.5 * (ex * ex + ey * ey + ez * ez) * inv_r2[i])
        total += term
        gx -= term * inv_r2[i] * ex
        gy -= term * inv_r2[i] * ey
        gz -= term * inv_r2[i] * ez
    sx, sy, sz = gx, gy, gz  # J^T g with J = I + sum_k cos(theta_k) disp_k wave_k^T
    for k in range(phase.shape[0]):
        c = math.cos(px * wave[0, k] + py * wave[1, k] + pz * wave[2, k] + phase[k])
        along = c * (disp[k, 0] * gx + disp[k, 1] * gy + disp[k, 2] * gz)
        sx += along * wave[0, k]
        sy += along * wave[1, k]
        sz += along * wave[2, k]
    radius = math.sqrt(px * px + py * py + pz * pz)
    edge = min(max((radius - 0.42) / 0.08, 0.0), 1.0)
    window = 1.0 - edge * edge * (3.0 - 2.0 * edge)
    slope = -6.0 * edge * (1.0 - edge) / 0.08 / radius if 0.0 < edge < 1.0 else 0.0  # dW/dr / r
    inner = math.exp(-total) * window
    outer = -math.expm1(-total) * slope
    nx, ny, nz = inner * sx + outer * px, inner * sy + outer * py, inner * sz + outer * pz
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    return min(abs(nx * dx + ny * dy + nz * dz) / norm, 1.0) if norm > 0.0 else 1.0


_facing_inline = jit(_facing, inline=True)


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _march(o, d, t_near, count, delta, centres, inv_r2, height, wave, phase, disp, cell_count, cell_blobs,
           knots, rgba, shading, reference_step, max_opacity, lit, stop_depth, rgb, opacity, depth):
    n_knots = knots.shape[0]
    cells = cell_count.shape[0]
    ambient, diffuse, specular, shininess = shading[0], shading[1], shading[2], shading[3]
    for r in range(o.shape[0]):
        ox, oy, oz, dx, dy, dz = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
        dt, t0 = delta[r], t_near[r]
        acc_t = 0.0
        tau_sum = 0.0
        for s in range(count[r]):
            t = t0 + (s + 0.5) * dt
            px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
            ix = min(max(int((px + 0.5) * cells), 0), cells - 1)
            iy = min(max(int((py + 0.5) * cells), 0), cells - 1)
            iz = min(max(int((pz + 0.5) * cells), 0), cells - 1)
            n_near = cell_count[ix, iy, iz]
            if n_near == 0:  # no value in this cell reaches the transfer function's first peak
                continue
            blobs = cell_blobs[ix, iy, iz]
            v = _value_inline(px, py, pz, centres, inv_r2, height, wave, phase, disp, blobs, n_near)
            k = 0  # the knot interval holding v (constant beyond the ends)
            while k < n_knots - 2 and v > knots[k + 1]:
                k += 1
            w = min(max((v - knots[k]) / (knots[k + 1] - knots[k]), 0.0), 1.0)
            alpha = rgba[k, 3] + w * (rgba[k + 1, 3] - rgba[k, 3])
            sigma = -math.log1p(-min(alpha, max_opacity)) / reference_step
            if sigma <= 0.0:
                continue
            light, glint = 1.0, 0.0
            if lit:
                cos = _facing_inline(px, py, pz, dx, dy, dz, centres, inv_r2, height, wave, phase, disp, blobs, n_near)
                light, glint = ambient + diffuse * cos, specular * cos**shininess
            weight = math.exp(-tau_sum) * -math.expm1(-sigma * dt)
            for c in range(3):
                colour = rgba[k, c] + w * (rgba[k + 1, c] - rgba[k, c])
                rgb[r, c] += weight * min(max(colour * light + glint, 0.0), 1.0)
            acc_t += weight * t
            tau_sum += sigma * dt
            if tau_sum >= stop_depth:
                break
        opacity[r] = -math.expm1(-tau_sum)
        depth[r] = acc_t / opacity[r] if opacity[r] > 0.0 else math.inf


_march_compiled = jit(_march)


def lowest_visible_value(tf: TransferFunction) -> float:
    """The largest value below which ``tf``'s opacity is zero (-inf where it never is)."""
    for k, alpha in enumerate(tf.opacities):
        if alpha > 0.0:
            return -math.inf if k == 0 else tf.knots[k - 1]
    return math.inf


CELLS = 64
"""Cells per axis of the table of blobs near each cell (over the box [-0.5, 0.5]^3)."""


@no_type_check  # compiled by numba: no runtime type checks (tests run jaxtyping's import hook)
def _cell_tables(centres, inv_r2, height, wave, phase, disp, lipschitz, needed, count, blobs):
    cells = count.shape[0]
    size = 1.0 / cells
    # how far a warped point can lie from the cell moved by its centre's warp
    slack = lipschitz * 0.5 * math.sqrt(3.0) * size
    for ix in range(cells):
        for iy in range(cells):
            for iz in range(cells):
                x, y, z = -0.5 + (ix + 0.5) * size, -0.5 + (iy + 0.5) * size, -0.5 + (iz + 0.5) * size
                wx, wy, wz = _warp_inline(x, y, z, wave, phase, disp)
                bound = 0.0
                n = 0
                for i in range(height.shape[0]):
                    gx = max(abs(centres[i, 0] - wx) - 0.5 * size - slack, 0.0)
                    gy = max(abs(centres[i, 1] - wy) - 0.5 * size - slack, 0.0)
                    gz = max(abs(centres[i, 2] - wz) - 0.5 * size - slack, 0.0)
                    exponent = 0.5 * (gx * gx + gy * gy + gz * gz) * inv_r2[i]
                    bound += height[i] * math.exp(-exponent)
                    if exponent < FAR_EXPONENT:
                        blobs[ix, iy, iz, n] = i
                        n += 1
                count[ix, iy, iz] = n if bound >= needed else 0


_cell_tables_compiled = jit(_cell_tables)


def cell_tables(
    field: ShellsField, lowest: float, cells: int = CELLS
) -> tuple[UInt8[np.ndarray, "c c c"], UInt8[np.ndarray, "c c c b"]]:
    """Per cell, how many blobs may reach it and which (their indices first). The warp moves a
    point of a cell at most its Lipschitz bound (the sum of the waves' displacement times wave
    number) times the point's distance from the centre away from the cell moved by the centre's
    warp; a blob reaches the cell when its exponent in that region is below ``FAR_EXPONENT``. A cell
    where even the sum of every blob's largest value there stays below the blobs' sum at ``lowest``
    has no visible value: a count of 0."""
    cpu = torch.device("cpu")
    centres, inv_r2, height = (a.numpy() for a in field.blobs(torch.float64, cpu))
    wave, phase, displacement = (a.numpy() for a in field.waves(torch.float64, cpu))
    lipschitz = float((np.linalg.norm(displacement, axis=-1) * np.linalg.norm(wave, axis=0)).sum())
    needed = -math.log1p(-min(lowest, 1.0 - 1e-12)) if lowest > 0.0 else -math.inf
    if height.shape[0] > 255:
        raise ValueError(f"the cell tables hold at most 255 blobs, the field has {height.shape[0]}")
    count = np.zeros((cells, cells, cells), dtype=np.uint8)
    blobs = np.zeros((cells, cells, cells, height.shape[0]), dtype=np.uint8)
    _cell_tables_compiled(centres, inv_r2, height, wave, phase, displacement, lipschitz, needed, count, blobs)
    return count, blobs


def serves_volume(volume: object, device: torch.device) -> bool:
    """Whether the compiled march draws ``volume`` (a lit or unlit DVR of a ``ShellsField``)."""
    return serves(device) and isinstance(volume, DvrVolume) and isinstance(volume.field, ShellsField)


def render_shells_rays(
    volume: DvrVolume, rays_o: Float[Tensor, "n 3"], rays_d: Float[Tensor, "n 3"], config: MarchConfig
) -> RayOutput:
    """``reference_renderer.render_rays`` of a ``ShellsField`` volume by the compiled loop; results
    in the rays' dtype."""
    field = volume.field
    if not isinstance(field, ShellsField):
        raise TypeError(f"the compiled march draws a ShellsField, not {type(field).__name__}")
    o64, d64 = rays_o.detach().cpu().double(), rays_d.detach().cpu().double()
    t_near, t_far, valid = ray_intervals(o64, d64, volume.bbox[0], volume.bbox[1], volume.support_radius, config.near)
    count, delta = uniform_segments(t_near, t_far, valid, config.step)
    cpu = torch.device("cpu")
    centres, inv_r2, height = (a.numpy() for a in field.blobs(torch.float64, cpu))
    wave, phase, displacement = (a.numpy() for a in field.waves(torch.float64, cpu))
    tf = volume.transfer_function
    rgba = np.array([(*c, a) for c, a in zip(tf.colours, tf.opacities, strict=True)], dtype=np.float64)
    s = config.shading
    shading = np.array([s.ambient, s.diffuse, s.specular, s.shininess])
    eps = config.early_stop_transmittance
    n = o64.shape[0]
    rgb, opacity, depth = np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    cell_count, cell_blobs = cell_tables(field, lowest_visible_value(tf))
    _march_compiled(
        o64.numpy(), d64.numpy(), t_near.numpy(), count.numpy(), delta.numpy(), centres, inv_r2, height, wave,
        phase, displacement, cell_count, cell_blobs, np.asarray(tf.knots, dtype=np.float64), rgba, shading,
        float(tf.reference_step), float(tf.max_opacity), volume.lit, -math.log(eps) if eps > 0 else math.inf,
        rgb, opacity, depth,
    )
    background = np.asarray(config.background, dtype=np.float64)
    rgb += (1.0 - opacity)[:, None] * background
    like = {"dtype": rays_o.dtype, "device": rays_o.device}
    return RayOutput(torch.from_numpy(rgb).to(**like), torch.from_numpy(opacity).to(**like),
                     torch.from_numpy(depth).to(**like))


def render_image_fast(
    volume: Volume, c2w: Float[Tensor, "4 4"], intrinsics: Intrinsics, config: MarchConfig
) -> RayOutput:
    """``reference_renderer.render_image``, by the compiled march where it serves the volume."""
    if not isinstance(volume, DvrVolume) or not serves_volume(volume, c2w.device):
        return render_image(volume, c2w, intrinsics, config)
    rays_o, rays_d = image_rays(c2w, intrinsics)  # [h, w, 3]
    return render_shells_rays(volume, rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), config)
