"""A synthetic indoor video with ground truth, for the tracking scenario (paper section 5).

The paper tracks a walking person in a 640x480 indoor video of 50 frames. We
have no video, so this module renders one, deterministically, with numpy only::

    from dtpf.entity.video import VideoScene, render
    video = render(VideoScene())          # cached: each process renders once
    video.frames[0]                       # (480, 640, 3) uint8 RGB, frame 1
    video.truth[0]                        # (cx, cy, radius) of frame 1, pixels

What is in it:

- background: a wall with a noise texture and a skirting board, a floor of
  perspective-free tiles with grout and grain, a door with frame and knob, a
  cabinet, a table, a window, and *clutter of the shirt's colour* (a red
  armchair, a red poster, a red box) that a colour tracker can confuse with
  the target;
- the target: a walking figure (torso ellipse, head, neck, arms and legs as
  thick segments) whose limbs swing with the gait phase, whose torso changes
  width with the walking direction and breathes, and whose size follows the
  depth (smaller when far, near the wall; larger when close to the camera);
- the path: it enters at the back left, comes towards the camera along a
  curve, turns, and walks away to the right, past the clutter;
- per frame: a slow illumination change (a gain of a few percent) and
  Gaussian pixel noise.

Ground truth per frame is the torso centre (cx, cy) and the radius of the
circle around the figure's body (half its height from head to hip), in
pixels. Frames are numbered 1 .. T as the filter's steps.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["VideoScene", "Video", "render", "SHIRT_RGB"]

#: Colour of the figure's shirt; the clutter objects have nearly the same colour.
SHIRT_RGB = (184, 38, 46)
_TROUSERS_RGB = (38, 46, 92)
_SKIN_RGB = (222, 178, 146)
_HAIR_RGB = (60, 40, 26)
_SHOES_RGB = (30, 26, 24)


@dataclass(frozen=True)
class VideoScene:
    """Parameters of the synthetic video; equal parameters give identical frames.

    Attributes
    ----------
    width, height : int
        Frame size in pixels (the paper: 640x480).
    frames : int
        Number of frames T (the paper: 50).
    seed : int
        Seed of the textures and the pixel noise (the path does not depend on it).
    noise_sd : float
        Standard deviation of the per-pixel Gaussian noise, in grey levels.
    illumination : float
        Relative amplitude of the slow global illumination change.
    """

    width: int = 640
    height: int = 480
    frames: int = 50
    seed: int = 0
    noise_sd: float = 4.0
    illumination: float = 0.06

    def __post_init__(self):
        if self.width < 160 or self.height < 120:
            raise ValueError(f"frame size must be at least 160x120, got {self.width}x{self.height}")
        if self.frames < 1:
            raise ValueError(f"frames must be at least 1, got {self.frames}")
        if not self.noise_sd >= 0 or not 0 <= self.illumination < 0.5:
            raise ValueError(f"noise_sd must be >= 0 and illumination in [0, 0.5), got "
                             f"{self.noise_sd!r}, {self.illumination!r}")


@dataclass(frozen=True)
class Video:
    """A rendered video: frames (T, H, W, 3) uint8 RGB and truth (T, 3) = (cx, cy, radius)."""

    scene: VideoScene
    frames: np.ndarray
    truth: np.ndarray

    def frame(self, number: int) -> np.ndarray:
        """Frame ``number`` (1 .. T), or a ValueError naming the number and T."""
        if not (isinstance(number, (int, np.integer)) and 1 <= number <= self.frames.shape[0]):
            raise ValueError(f"unknown frame {number!r}; the video has frames 1 .. {self.frames.shape[0]}")
        return self.frames[number - 1]


# --- the path and the pose -------------------------------------------------------------------------

def _path(scene: VideoScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Foot point (x, y) and body height h of the figure per frame, in pixels.

    The figure walks along a curve in the floor plane: from the back left
    towards the camera, then turns and walks away to the right. Its height
    in the image grows with the foot's distance below the horizon (a pinhole
    camera over a flat floor: h proportional to y_foot - y_horizon).
    """
    t = np.linspace(0.0, 1.0, scene.frames) if scene.frames > 1 else np.zeros(1)
    w, h = scene.width, scene.height
    horizon = 0.30 * h
    foot_x = w * (0.14 + 0.70 * t + 0.07 * np.sin(2.2 * math.pi * t))
    # Depth: near the wall at the start, close to the camera in the middle, away at the end.
    foot_y = h * (0.66 + 0.26 * np.sin(math.pi * np.clip(1.25 * t, 0.0, 1.0)) ** 1.5 - 0.06 * t)
    height = 0.98 * (foot_y - horizon)
    return foot_x, foot_y, height


def _pose(scene: VideoScene):
    """Everything the figure's drawing needs, per frame (arrays of length T)."""
    foot_x, foot_y, height = _path(scene)
    step_length = np.hypot(np.gradient(foot_x), np.gradient(foot_y)) if scene.frames > 1 else np.zeros(1)
    # Gait phase advances with the distance walked in body heights (about a stride per 0.7 heights).
    phase = 2.0 * math.pi * np.cumsum(step_length / np.maximum(height, 1.0)) / 0.7
    heading = np.arctan2(np.gradient(foot_y), np.gradient(foot_x)) if scene.frames > 1 else np.zeros(1)
    # Walking across the image shows the side (narrow torso); towards/away the front (wide).
    frontal = np.abs(np.sin(heading))
    bob = 0.012 * height * np.cos(2.0 * phase)
    return foot_x, foot_y, height, phase, frontal, bob


def _truth(scene: VideoScene) -> np.ndarray:
    """(T, 3): torso centre (cx, cy) and the radius of the circle around head and torso."""
    foot_x, foot_y, height, _, _, bob = _pose(scene)
    cx = foot_x
    cy = foot_y - 0.64 * height + bob
    radius = 0.22 * height
    return np.stack([cx, cy, radius], axis=1)


# --- drawing helpers (each touches only the shape's bounding box) ----------------------------------

def _box(image, x0, y0, x1, y1):
    h, w = image.shape[:2]
    x0, y0 = max(0, int(math.floor(x0))), max(0, int(math.floor(y0)))
    x1, y1 = min(w, int(math.ceil(x1)) + 1), min(h, int(math.ceil(y1)) + 1)
    if x0 >= x1 or y0 >= y1:
        return None
    yy, xx = np.mgrid[y0:y1, x0:x1]
    return (slice(y0, y1), slice(x0, x1)), xx + 0.5, yy + 0.5


def _fill(image, region, mask, colour):
    patch = image[region]
    patch[mask] = colour


def fill_ellipse(image, cx, cy, a, b, colour, angle=0.0):
    """Paint the ellipse with centre (cx, cy), semi-axes a (x) and b (y), rotated by ``angle`` rad."""
    r = max(a, b)
    box = _box(image, cx - r, cy - r, cx + r, cy + r)
    if box is None:
        return
    region, xx, yy = box
    c, s = math.cos(angle), math.sin(angle)
    u = (xx - cx) * c + (yy - cy) * s
    v = -(xx - cx) * s + (yy - cy) * c
    _fill(image, region, (u / a) ** 2 + (v / b) ** 2 <= 1.0, colour)


def fill_segment(image, x0, y0, x1, y1, thickness, colour):
    """Paint a thick segment (a capsule of the given thickness) from (x0, y0) to (x1, y1)."""
    r = thickness / 2.0
    box = _box(image, min(x0, x1) - r, min(y0, y1) - r, max(x0, x1) + r, max(y0, y1) + r)
    if box is None:
        return
    region, xx, yy = box
    dx, dy = x1 - x0, y1 - y0
    length2 = dx * dx + dy * dy
    t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / length2, 0.0, 1.0) if length2 > 0 else 0.0
    _fill(image, region, (xx - x0 - t * dx) ** 2 + (yy - y0 - t * dy) ** 2 <= r * r, colour)


def fill_rect(image, x0, y0, x1, y1, colour):
    """Paint the axis-aligned rectangle [x0, x1) x [y0, y1)."""
    h, w = image.shape[:2]
    image[max(0, int(y0)):min(h, int(y1)), max(0, int(x0)):min(w, int(x1))] = colour


# --- background -----------------------------------------------------------------------------------

def _value_noise(rng, height, width, cell):
    """Smooth noise in [-1, 1]: a coarse random grid, bilinearly interpolated."""
    gh, gw = height // cell + 2, width // cell + 2
    grid = rng.uniform(-1.0, 1.0, size=(gh, gw))
    y = np.arange(height) / cell
    x = np.arange(width) / cell
    y0, x0 = y.astype(int), x.astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    a = grid[y0][:, x0]
    b = grid[y0][:, x0 + 1]
    c = grid[y0 + 1][:, x0]
    d = grid[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _background(scene: VideoScene) -> np.ndarray:
    """The static room, (H, W, 3) float32 in grey levels."""
    rng = np.random.default_rng([scene.seed, 1])
    h, w = scene.height, scene.width
    image = np.empty((h, w, 3), dtype=np.float32)
    wall_bottom = int(0.36 * h)
    # Wall: warm off-white plaster with a two-scale texture.
    texture = 10.0 * _value_noise(rng, h, w, 24) + 5.0 * _value_noise(rng, h, w, 5)
    image[:] = np.array([206, 198, 180], dtype=np.float32)
    image += texture[:, :, None]
    # Floor: tiles with grout and grain.
    yy, xx = np.mgrid[wall_bottom:h, 0:w]
    tile = 52
    parity = ((xx // tile) + (yy // (tile // 2))) % 2
    floor = np.where(parity[:, :, None] == 1, np.array([150, 128, 100], np.float32), np.array([166, 144, 114], np.float32))
    grout = ((xx % tile) < 2) | ((yy % (tile // 2)) < 2)
    floor = np.where(grout[:, :, None], np.array([108, 98, 86], np.float32), floor)
    floor = floor + 7.0 * _value_noise(rng, h - wall_bottom, w, 9)[:, :, None]
    image[wall_bottom:] = floor
    fill_rect(image, 0, wall_bottom - 8, w, wall_bottom, (120, 100, 80))                # skirting board
    # Door with frame and knob.
    dx0, dx1 = 0.62 * w, 0.74 * w
    fill_rect(image, dx0 - 6, 0.04 * h, dx1 + 6, wall_bottom, (96, 72, 50))
    fill_rect(image, dx0, 0.06 * h, dx1, wall_bottom, (140, 100, 64))
    for y0 in (0.10, 0.22):
        fill_rect(image, dx0 + 8, y0 * h, dx1 - 8, (y0 + 0.09) * h, (128, 90, 58))
    fill_ellipse(image, dx1 - 12, 0.22 * h, 4, 4, (214, 190, 90))
    # Window with a sky-blue pane and mullions.
    fill_rect(image, 0.06 * w, 0.06 * h, 0.24 * w, 0.24 * h, (236, 236, 230))
    fill_rect(image, 0.07 * w, 0.075 * h, 0.23 * w, 0.225 * h, (150, 190, 222))
    fill_rect(image, 0.148 * w, 0.07 * h, 0.152 * w, 0.23 * h, (236, 236, 230))
    # Cabinet and table.
    fill_rect(image, 0.80 * w, 0.10 * h, 0.96 * w, 0.40 * h, (110, 84, 60))
    fill_rect(image, 0.81 * w, 0.12 * h, 0.875 * w, 0.38 * h, (124, 96, 70))
    fill_rect(image, 0.885 * w, 0.12 * h, 0.95 * w, 0.38 * h, (124, 96, 70))
    fill_rect(image, 0.30 * w, 0.26 * h, 0.50 * w, 0.29 * h, (90, 70, 52))
    for x in (0.31, 0.48):
        fill_rect(image, x * w, 0.29 * h, (x + 0.012) * w, 0.40 * h, (90, 70, 52))
    # Clutter in the shirt's colour: an armchair, a poster, a box.
    red = np.array(SHIRT_RGB, dtype=np.float32)
    fill_rect(image, 0.40 * w, 0.10 * h, 0.47 * w, 0.22 * h, red * 0.97)                # poster
    fill_rect(image, 0.41 * w, 0.12 * h, 0.46 * w, 0.14 * h, (230, 220, 200))
    fill_rect(image, 0.25 * w, 0.56 * h, 0.36 * w, 0.70 * h, red * 1.03)                # armchair seat
    fill_rect(image, 0.25 * w, 0.44 * h, 0.36 * w, 0.58 * h, red * 0.90)                # armchair back
    fill_rect(image, 0.23 * w, 0.50 * h, 0.26 * w, 0.70 * h, red * 0.85)                # arm rests
    fill_rect(image, 0.35 * w, 0.50 * h, 0.38 * w, 0.70 * h, red * 0.85)
    fill_rect(image, 0.86 * w, 0.74 * h, 0.95 * w, 0.86 * h, red * 1.05)                # box
    return image


# --- the figure ------------------------------------------------------------------------------------

def _draw_figure(image, foot_x, foot_y, height, phase, frontal, bob):
    """Paint the walking figure whose feet are at (foot_x, foot_y) and who is ``height`` tall."""
    s = height
    hip_y = foot_y - 0.47 * s + bob
    shoulder_y = foot_y - 0.80 * s + bob
    torso_half_width = s * (0.10 + 0.055 * frontal) * (1.0 + 0.03 * math.sin(0.5 * phase))
    limb = s * 0.065
    swing = 0.45 * math.sin(phase)
    leg_length, arm_length = 0.47 * s, 0.36 * s
    # Legs (behind the torso): thigh plus shin, knees bending with the gait.
    for side in (-1.0, 1.0):
        angle = side * swing
        hip_x = foot_x + side * 0.35 * torso_half_width
        knee_x = hip_x + 0.5 * leg_length * math.sin(angle)
        knee_y = hip_y + 0.5 * leg_length * math.cos(angle)
        bend = max(0.0, -side * math.cos(phase)) * 0.5
        ankle_x = knee_x + 0.5 * leg_length * math.sin(angle - bend)
        ankle_y = knee_y + 0.5 * leg_length * math.cos(angle - bend)
        fill_segment(image, hip_x, hip_y, knee_x, knee_y, 1.3 * limb, _TROUSERS_RGB)
        fill_segment(image, knee_x, knee_y, ankle_x, ankle_y, 1.1 * limb, _TROUSERS_RGB)
        fill_ellipse(image, ankle_x + 0.03 * s, ankle_y, 0.05 * s, 0.022 * s, _SHOES_RGB)
    # Torso, neck and head.
    fill_ellipse(image, foot_x, 0.5 * (hip_y + shoulder_y), torso_half_width, 0.5 * (hip_y - shoulder_y) + 0.02 * s,
                 SHIRT_RGB)
    fill_segment(image, foot_x, shoulder_y, foot_x, shoulder_y - 0.05 * s, 0.05 * s, _SKIN_RGB)
    head_y = shoulder_y - 0.11 * s
    fill_ellipse(image, foot_x, head_y, 0.062 * s, 0.075 * s, _SKIN_RGB)
    fill_ellipse(image, foot_x, head_y - 0.04 * s, 0.064 * s, 0.04 * s, _HAIR_RGB)
    # Arms swing opposite to the legs: upper arm in the shirt's colour, forearm skin.
    for side in (-1.0, 1.0):
        angle = -side * swing * 0.9
        sx = foot_x + side * 0.95 * torso_half_width
        elbow_x = sx + 0.5 * arm_length * math.sin(angle)
        elbow_y = shoulder_y + 0.03 * s + 0.5 * arm_length * math.cos(angle)
        hand_x = elbow_x + 0.5 * arm_length * math.sin(1.4 * angle)
        hand_y = elbow_y + 0.5 * arm_length * math.cos(1.4 * angle)
        fill_segment(image, sx, shoulder_y + 0.03 * s, elbow_x, elbow_y, 0.9 * limb, SHIRT_RGB)
        fill_segment(image, elbow_x, elbow_y, hand_x, hand_y, 0.75 * limb, _SKIN_RGB)


def _render(scene: VideoScene) -> Video:
    background = _background(scene)
    truth = _truth(scene)
    foot_x, foot_y, height, phase, frontal, bob = _pose(scene)
    rng = np.random.default_rng([scene.seed, 2])
    frames = np.empty((scene.frames, scene.height, scene.width, 3), dtype=np.uint8)
    gains = 1.0 + scene.illumination * np.sin(np.linspace(0.0, 2.0 * math.pi, scene.frames) + 0.7)
    noise = np.empty((scene.height, scene.width, 3), dtype=np.float32)
    for i in range(scene.frames):
        image = background.copy()
        _draw_figure(image, foot_x[i], foot_y[i], height[i], phase[i], frontal[i], bob[i])
        image *= np.float32(gains[i])
        rng.standard_normal(out=noise, dtype=np.float32)
        image += np.float32(scene.noise_sd) * noise
        np.clip(image, 0.0, 255.0, out=image)
        frames[i] = image.astype(np.uint8)  # rint would cost more; truncation is the same for every frame
    frames.flags.writeable = False
    truth.flags.writeable = False
    return Video(scene, frames, truth)


@functools.lru_cache(maxsize=4)
def render(scene: VideoScene = VideoScene()) -> Video:
    """The frames and ground truth of ``scene``, rendered once per process (cached; read-only arrays)."""
    return _render(scene)
