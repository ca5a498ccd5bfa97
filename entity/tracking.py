"""The video tracking scenario (paper section 5): a colour-histogram particle filter.

State x = (cx, cy, vx, vy, s): the centre of the circle around the target in
pixels, its velocity in pixels per frame, and its scale s, the radius of the
circle relative to the radius the user drew around the target on frame 1.
The observation of step k is the frame number k as a (1,) array: every
process renders the same deterministic video (:mod:`dtpf.entity.video`) from the
model's parameters, so only the frame number crosses Zenoh::

    from dtpf.entity import models
    model = models.get("video")
    truth, observations = model.simulate(50, rng)      # truth (50, 5), observations [[1], .., [50]]
    model.log_likelihood(particles, observations[k - 1], k)

Laws:

- Prior (frame 1, where the paper selects the target with a circle): centre
  N(true centre, prior_position_sd^2) per axis, velocity N(0, prior_velocity_sd^2),
  log s ~ N(0, prior_log_scale_sd^2).
- Propagation, near-constant velocity (a white-noise acceleration model with a
  random walk on log-scale)::

      v_k = v_(k-1) + a_k,            a_k ~ N(0, accel_sd^2 I)
      c_k = c_(k-1) + v_k + e_k,      e_k ~ N(0, position_sd^2 I)
      log s_k = log s_(k-1) + g_k,    g_k ~ N(0, log_scale_sd^2)

  A scale that is not positive (the DT rules of Eq. 29-30 can move a state
  anywhere) stays where it is and keeps the floor likelihood below.
- Likelihood (Perez et al. 2002, Comaniciu et al. 2003): the kernel-weighted
  colour histogram q(x) of the disc of radius s r_1 at c, in HSV bins, is
  compared with the reference histogram p of frame 1 at the true circle by
  the Bhattacharyya distance, both weighted by the corrected background
  weights v of Ning et al. (2012) (see ``_reference``), so that the floor and
  the wall, which fill part of every circle, count less than the figure::

      rho(x) = sum_u sqrt(q_u(x) p_u),   d(x) = sqrt(1 - rho(x)),
      log p(z_k | x) = -d(x)^2 / (2 sigma^2)

  The disc is sampled at a fixed set of P points of the unit disc (a Vogel
  spiral) scaled by each particle's radius; a point outside the image counts
  in an extra "outside" bin that the reference does not have. A state whose
  centre is outside the image, or whose scale is outside [min_scale,
  max_scale] or not finite, gets d = 1, the lowest value, -1 / (2 sigma^2):
  finite, so the weights never all vanish.

Vectorised: the bin index of every pixel is computed once per frame; one
``np.bincount`` over N x P indices gives all N histograms.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from dtpf.entity.base import StateSpaceModel
from dtpf.entity.video import Video, VideoScene, render

__all__ = ["VideoTrackingModel", "disc_offsets", "hsv_bins", "encode_jpeg", "FRAME_SCENARIO_HINT"]

#: Why the simulating system-layer policies cannot run on a video.
FRAME_SCENARIO_HINT = ("the video scenario does not support the simulating system-layer policies (rule, "
                       "predictive): a frame cannot be drawn from p(z | x); use --policy fixed")


def disc_offsets(count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread evenly over the unit disc (a Vogel spiral) and their kernel weights.

    Returns (P, 2) offsets (dx, dy) with |offset| < 1 and (P,) Epanechnikov
    weights 1 - |offset|^2, normalised to sum 1, which count the centre of the
    target more than its border (Comaniciu et al. 2003, Eq. 2).
    """
    if count < 1:
        raise ValueError(f"the number of disc points must be at least 1, got {count}")
    i = np.arange(count) + 0.5
    radius = np.sqrt(i / count)
    angle = i * math.pi * (3.0 - math.sqrt(5.0))
    offsets = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)
    kernel = 1.0 - radius * radius
    return offsets, kernel / kernel.sum()


def hsv_bins(frame: np.ndarray, hue_bins: int, saturation_bins: int, value_bins: int) -> np.ndarray:
    """The histogram bin of every pixel of an RGB frame: (H, W) int32 in [0, B).

    Pixels with enough saturation and value are binned by hue, saturation and
    value (hue_bins x saturation_bins x value_bins bins); grey or dark
    pixels, whose hue means nothing, by value alone (value_bins bins after
    those), as Perez et al. (2002) do. B = (hue_bins * saturation_bins + 1) * value_bins.
    """
    rgb = frame.astype(np.float32) / 255.0
    top = rgb.max(axis=2)
    spread = top - rgb.min(axis=2)
    saturation = np.where(top > 0, spread / np.maximum(top, 1e-6), 0.0)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    safe = np.maximum(spread, 1e-6)
    hue = np.where(top == r, (g - b) / safe, np.where(top == g, 2.0 + (b - r) / safe, 4.0 + (r - g) / safe))
    hue = (hue / 6.0) % 1.0
    coloured = (saturation > 0.15) & (top > 0.15)
    h_bin = np.minimum((hue * hue_bins).astype(np.int32), hue_bins - 1)
    s_bin = np.clip(((saturation - 0.15) / 0.85 * saturation_bins).astype(np.int32), 0, saturation_bins - 1)
    v_bin = np.minimum((top * value_bins).astype(np.int32), value_bins - 1)
    colour_bin = (h_bin * saturation_bins + s_bin) * value_bins + v_bin
    grey_bin = hue_bins * saturation_bins * value_bins + v_bin
    return np.where(coloured, colour_bin, grey_bin).astype(np.int32)


@dataclass(frozen=True, eq=False)
class VideoTrackingModel(StateSpaceModel):
    """Colour-histogram tracking of the walking figure of :mod:`dtpf.entity.video` (section 5).

    Parameters are the video's (``scene``), the histogram's, the likelihood's
    sigma and the noise of the motion model; defaults are tuned for the
    default scene. Every process that builds this model with the same
    parameters sees the same frames.
    """

    name: str = "video"
    scene: VideoScene = field(default_factory=VideoScene)
    hue_bins: int = 12
    saturation_bins: int = 3
    value_bins: int = 3
    background_ring: float = 2.5
    disc_points: int = 96
    sigma: float = 0.2
    accel_sd: float = 3.0
    position_sd: float = 2.0
    log_scale_sd: float = 0.04
    prior_position_sd: float = 6.0
    prior_velocity_sd: float = 4.0
    prior_log_scale_sd: float = 0.08
    min_scale: float = 0.25
    max_scale: float = 4.0
    dim: int = 5
    obs_dim: int = 1
    #: The system layer's simulating policies need sample_observation; a video cannot give it.
    samples_observations: bool = False

    # --- the video and what is precomputed from it ---

    @property
    def video(self) -> Video:
        """The rendered video (cached per process)."""
        return render(self.scene)

    @property
    def n_bins(self) -> int:
        """B, the colour bins; index B is the 'outside the image' bin."""
        return (self.hue_bins * self.saturation_bins + 1) * self.value_bins

    @property
    def radius1(self) -> float:
        """r_1, the radius of the circle around the target on frame 1 (scale 1)."""
        return float(self.video.truth[0, 2])

    #: Most particles drawn over a frame (every ceil(N / this)-th, as the point cloud chooses).
    annotated_particles: int = 300

    def step_messages(self, header: dict, particles=None, weights=None, mean=None) -> list:
        """The frame of the step as a ``foxglove.CompressedImage`` (base64 JPEG) and, given the step's
        particles, a ``foxglove.ImageAnnotations`` at the same time: the particles' positions as points,
        the estimate's circle (its position and scale times r_1)."""
        import base64

        from dtpf.messages.foxglove import (
            BASE64_CHECKED,
            CircleAnnotation,
            Color,
            CompressedImage,
            ImageAnnotations,
            Point2,
            PointsAnnotation,
        )
        from dtpf.messages.models import Time

        stamp = Time.now()
        frame = encode_jpeg(self.video.frame(header["step"]))
        out = [CompressedImage.model_validate(dict(**header, timestamp=stamp, frame_id="camera", format="jpeg",
                                                   data=base64.b64encode(frame).decode("ascii")),
                                              context=BASE64_CHECKED)]
        if particles is None or mean is None:
            return out
        stride = max(1, math.ceil(len(particles) / self.annotated_particles))
        drawn = np.asarray(particles)[::stride, :2]
        finite = np.isfinite(drawn).all(axis=1)
        yellow, red, clear = Color(r=1, g=0.85, b=0, a=0.8), Color(r=1, g=0.1, b=0.1, a=1), Color(r=0, g=0, b=0, a=0)
        points = PointsAnnotation(timestamp=stamp, type=1, points=[Point2(x=float(x), y=float(y)) for x, y in drawn[finite]],
                                  outline_color=yellow, fill_color=yellow, thickness=2.0)
        scale = float(mean[4]) if np.isfinite(mean[4]) and mean[4] > 0 else 1.0
        circles = [CircleAnnotation(timestamp=stamp, position=Point2(x=float(mean[0]), y=float(mean[1])),
                                    diameter=2.0 * scale * self.radius1, thickness=2.0, fill_color=clear,
                                    outline_color=red)] if np.isfinite(mean[:2]).all() else []
        out.append(ImageAnnotations(**header, circles=circles, points=[points]))
        return out

    def frame_number(self, observation) -> int:
        """The frame an observation names, or a ValueError naming the value and the frame range."""
        z = np.asarray(observation, dtype=np.float64).reshape(-1)
        frames = self.scene.frames
        if z.size != 1 or not np.isfinite(z[0]) or z[0] != round(z[0]) or not 1 <= z[0] <= frames:
            raise ValueError(f"unknown frame {z.tolist()!r}; the observation of the video scenario is a frame "
                             f"number 1 .. {frames}")
        return int(z[0])

    def bin_image(self, number: int) -> np.ndarray:
        """(H*W,) bin index of every pixel of frame ``number`` (cached)."""
        return _bin_image(self, number)

    def reference(self) -> np.ndarray:
        """p, the background-weighted reference histogram (B + 1,) of frame 1 at the true circle."""
        return _reference(self)[0]

    def bin_weights(self) -> np.ndarray:
        """v_u = min(o* / o_u, 1) of the background histogram o around the target on frame 1 (B + 1,)."""
        return _reference(self)[1]

    # --- the StateSpaceModel laws ---

    def true_states(self, steps: int | None = None) -> np.ndarray:
        """(T, 5) ground truth: centre, velocity (central finite differences), scale r_k / r_1."""
        truth = self.video.truth
        steps = truth.shape[0] if steps is None else steps
        centre = truth[:, :2]
        velocity = np.gradient(centre, axis=0) if truth.shape[0] > 1 else np.zeros_like(centre)
        scale = truth[:, 2:3] / truth[0, 2]
        return np.concatenate([centre, velocity, scale], axis=1)[:steps].copy()

    def initial_particles(self, n, rng):
        truth = self.true_states(1)[0]
        out = np.empty((n, 5))
        out[:, 0:2] = truth[0:2] + self.prior_position_sd * rng.standard_normal((n, 2))
        out[:, 2:4] = self.prior_velocity_sd * rng.standard_normal((n, 2))
        out[:, 4] = np.exp(self.prior_log_scale_sd * rng.standard_normal(n))
        return out

    def propagation_noise(self, n, k, rng):
        return rng.standard_normal((n, 5))

    def propagate(self, particles, k, rng, noise=None):
        if noise is None:
            noise = self.propagation_noise(particles.shape[0], k, rng)
        out = np.empty_like(particles)
        out[:, 2:4] = particles[:, 2:4] + self.accel_sd * noise[:, 0:2]
        out[:, 0:2] = particles[:, 0:2] + out[:, 2:4] + self.position_sd * noise[:, 2:4]
        out[:, 4] = particles[:, 4] * np.exp(self.log_scale_sd * noise[:, 4])
        return out

    def log_likelihood(self, particles, observation, k):
        d2 = self.distance2(particles, self.frame_number(observation))
        return -d2 / (2.0 * self.sigma * self.sigma)

    def distance2(self, particles: np.ndarray, number: int) -> np.ndarray:
        """d(x)^2 = 1 - rho(x) for every particle on frame ``number`` (vectorised): (N, 5) -> (N,)."""
        x = np.asarray(particles, dtype=np.float64)
        n = x.shape[0]
        width, height = self.scene.width, self.scene.height
        offsets, kernel = _disc(self.disc_points)
        cx, cy, scale = x[:, 0], x[:, 1], x[:, 4]
        with np.errstate(invalid="ignore"):
            valid = (np.isfinite(cx) & np.isfinite(cy) & (scale >= self.min_scale) & (scale <= self.max_scale)
                     & (cx >= 0) & (cx < width) & (cy >= 0) & (cy < height))
        radius = np.where(valid, scale, 0.0) * self.radius1
        px = np.where(valid, cx, 0.0)[:, None] + radius[:, None] * offsets[None, :, 0]
        py = np.where(valid, cy, 0.0)[:, None] + radius[:, None] * offsets[None, :, 1]
        ix = np.floor(px).astype(np.int32)
        iy = np.floor(py).astype(np.int32)
        inside = (ix >= 0) & (ix < width) & (iy >= 0) & (iy < height)
        pixel = np.where(inside, iy * width + ix, 0)
        bins = np.where(inside, self.bin_image(number)[pixel], self.n_bins)
        bins += (np.arange(n, dtype=np.int32) * (self.n_bins + 1))[:, None]
        histograms = np.bincount(bins.ravel(), weights=np.broadcast_to(kernel, bins.shape).ravel(),
                                 minlength=n * (self.n_bins + 1)).reshape(n, self.n_bins + 1)
        histograms *= self.bin_weights()[None, :]
        totals = histograms.sum(axis=1, keepdims=True)
        histograms /= np.where(totals > 0, totals, 1.0)
        rho = np.sqrt(histograms) @ np.sqrt(self.reference())
        return np.where(valid, np.clip(1.0 - rho, 0.0, 1.0), 1.0)

    def sample_observation(self, states, k, rng):
        raise NotImplementedError(FRAME_SCENARIO_HINT)

    @property
    def max_steps(self) -> int:
        """A simulation of the video has as many steps as it has frames."""
        return self.scene.frames

    def simulate(self, steps, rng):
        frames = self.scene.frames
        if not 1 <= steps <= frames:
            raise ValueError(f"steps must be in 1 .. {frames} (the video has {frames} frames), got {steps}")
        observations = np.arange(1.0, steps + 1.0)[:, None]
        return self.true_states(steps), observations


def encode_jpeg(frame: np.ndarray, quality: int = 85) -> bytes:
    """The JPEG file of an (H, W, 3) uint8 RGB frame (Pillow), as Foxglove's CompressedImage carries it."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(frame), mode="RGB").save(buffer, format="JPEG", quality=quality)
    return buffer.getvalue()


@functools.lru_cache(maxsize=8)
def _disc(count: int) -> tuple[np.ndarray, np.ndarray]:
    return disc_offsets(count)


@functools.lru_cache(maxsize=512)
def _bin_image(model: VideoTrackingModel, number: int) -> np.ndarray:
    frame = model.video.frame(number)
    bins = hsv_bins(frame, model.hue_bins, model.saturation_bins, model.value_bins).ravel()
    bins.flags.writeable = False
    return bins


@functools.lru_cache(maxsize=8)
def _reference(model: VideoTrackingModel) -> tuple[np.ndarray, np.ndarray]:
    """Reference histogram and bin weights of the corrected background-weighted histogram.

    Ning et al. (2012): o is the colour histogram of the ring between r_1 and
    ``background_ring`` r_1 around the target on frame 1, o* its smallest
    non-zero entry, v_u = min(o* / o_u, 1) (1 where o_u = 0). Colours common
    around the target (the floor, the wall) count less in the reference and
    in every candidate, so the figure's own colours decide.
    """
    truth = model.true_states(1)[0]
    width, height = model.scene.width, model.scene.height
    bins1 = model.bin_image(1)
    outside = model.n_bins

    def histogram(points: np.ndarray, weights: np.ndarray) -> np.ndarray:
        px = np.floor(points[:, 0]).astype(np.int64)
        py = np.floor(points[:, 1]).astype(np.int64)
        inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
        bins = np.where(inside, bins1[np.where(inside, py * width + px, 0)], outside)
        return np.bincount(bins, weights=weights, minlength=outside + 1)

    yy, xx = np.mgrid[0:height, 0:width]
    distance = np.hypot(xx + 0.5 - truth[0], yy + 0.5 - truth[1])
    ring = (distance >= model.radius1) & (distance < model.background_ring * model.radius1)
    background = histogram(np.stack([xx[ring] + 0.5, yy[ring] + 0.5], axis=1), np.ones(int(ring.sum())))
    background[outside] = 0.0
    positive = background[background > 0]
    weights = np.ones(outside + 1)
    if positive.size:
        weights = np.where(background > 0, np.minimum(positive.min() / np.maximum(background, 1e-300), 1.0), 1.0)
    weights[outside] = 1.0
    offsets, kernel = _disc(model.disc_points)
    reference = histogram(truth[:2] + model.radius1 * offsets, kernel) * weights
    reference[outside] = 0.0  # the reference holds no 'outside' mass
    reference /= reference.sum()
    reference.flags.writeable = False
    weights.flags.writeable = False
    return reference, weights
