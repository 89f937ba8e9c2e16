"""``der bag render``: a top-down animation of recorded episodes, drawn from a bag's scene markers.

Each recorded decision step becomes one frame (:mod:`der_ros.offline.scene_frames`): the road (every
lane a ribbon as wide as the lane, a thin gap between neighbours as the lane marking), every
vehicle a rotated rectangle in its role's colour (:data:`der_ros.contract.ROLE_COLOURS`; the ego
red with a black outline), and a caption with the episode, the step, the action taken from there,
the reward of arriving there, the return so far and, on the last frame, the outcome.

View: a network that fits in ``fit_extent`` metres (the ring, ~125 m across) is drawn whole and
still; a larger one (the urban network, ~2 km) is drawn in a ``window``-metre square that follows
the ego, north up, so vehicles stay a few pixels wide instead of dots. :func:`frame_view` gives a
frame's world-to-pixel mapping (tests use it to find the ego's pixel).

Drawn with Pillow's ``ImageDraw`` on an RGB canvas and written by :mod:`der_ros.offline.animation`
(GIF with a fixed palette, or MP4): no matplotlib figure per frame, so a 40-step episode renders
in well under its 20 simulated seconds (figure in ``bench/render.py``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

from der_ros.bag.reader import BagReader
from der_ros.contract import ACTION_NAMES, EGO_ROLE, LANE_COLOUR, ROLE_COLOURS, TRAFFIC_ROLE, LaneLine, VehicleMarker
from der_ros.offline.animation import check_output, write_animation
from der_ros.offline.scene_frames import EpisodeFrames, Frame, SceneRecording, read_scene

__all__ = ["RenderOptions", "View", "RenderResult", "network_view", "follow_view", "frame_view", "draw_frame",
           "render_recording", "render_bag", "Caption", "caption_lines", "PALETTE"]  # fmt: skip

RGB = tuple[int, int, int]


def _rgb(rgba: tuple[float, ...]) -> RGB:
    return int(round(rgba[0] * 255)), int(round(rgba[1] * 255)), int(round(rgba[2] * 255))


BACKGROUND: RGB = (236, 236, 228)
ROAD: RGB = _rgb(LANE_COLOUR)
BAND: RGB = (28, 28, 34)
TEXT: RGB = (250, 250, 250)
OUTLINE: RGB = (20, 20, 20)
ROLE_RGB: dict[str, RGB] = {role: _rgb(c) for role, c in ROLE_COLOURS.items()}
#: every colour a frame is drawn with, plus a ramp from the caption band to the text colour for the
#: font's anti-aliased edges: the GIF's palette, so the drawn colours stay exact
#: a command the safety node vetoed: the marker on the ego and the caption's veto text
VETO: RGB = (255, 170, 0)
PALETTE: list[RGB] = [BACKGROUND, ROAD, BAND, TEXT, OUTLINE, *ROLE_RGB.values()] + [
    tuple(int(round(b + (t - b) * k / 15)) for b, t in zip(BAND, TEXT)) for k in range(1, 15)  # type: ignore[misc]
] + [VETO]


@dataclass(frozen=True)
class RenderOptions:
    """Size and pacing of the animation."""

    width: int = 640
    #: height of the map area; the caption band comes on top of it
    height: int = 640
    caption_height: int = 64
    #: frames per second; None: twice real time (2 / the decision step)
    fps: float | None = None
    #: side of the square window that follows the ego, m; None: the whole network if it fits in
    #: ``fit_extent``, else ``follow_window``; 0: always the whole network
    window: float | None = None
    fit_extent: float = 300.0
    follow_window: float = 150.0
    margin_px: int = 12

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if value < 64 or value % 16:
                raise ValueError(f"render {name} = {value}, expected a multiple of 16, at least 64 (video encoders)")
        if self.caption_height < 0 or self.caption_height % 16:
            raise ValueError(f"render caption_height = {self.caption_height}, expected a multiple of 16 >= 0")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"render fps = {self.fps}, expected > 0")
        if self.window is not None and self.window < 0:
            raise ValueError(f"render window = {self.window} m, expected >= 0 (0: the whole network)")


@dataclass(frozen=True)
class View:
    """World (map frame, m) to image pixels: ``scale`` px/m, world point (x0, y1) at the map area's
    top-left corner, which sits ``top`` pixels below the image's top (under the caption)."""

    scale: float
    x0: float
    y1: float
    top: int

    def project(self, x: float, y: float) -> tuple[float, float]:
        return (x - self.x0) * self.scale, self.top + (self.y1 - y) * self.scale


def _bounds(lanes: list[LaneLine], vehicles: tuple[VehicleMarker, ...] = ()) -> tuple[float, float, float, float]:
    xs: list[float] = []
    ys: list[float] = []
    for lane in lanes:
        xs += [float(lane.points[:, 0].min()) - lane.width, float(lane.points[:, 0].max()) + lane.width]
        ys += [float(lane.points[:, 1].min()) - lane.width, float(lane.points[:, 1].max()) + lane.width]
    for v in vehicles:
        xs += [v.x - v.length, v.x + v.length]
        ys += [v.y - v.length, v.y + v.length]
    if not xs:
        return -50.0, -50.0, 50.0, 50.0
    return min(xs), min(ys), max(xs), max(ys)


def network_view(lanes: list[LaneLine], opts: RenderOptions, vehicles: tuple[VehicleMarker, ...] = ()) -> View:
    """The whole road (and ``vehicles``) fitted into the map area, centred."""
    x0, y0, x1, y1 = _bounds(lanes, vehicles)
    m = opts.margin_px
    scale = min((opts.width - 2 * m) / max(x1 - x0, 1e-6), (opts.height - 2 * m) / max(y1 - y0, 1e-6))
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return View(scale, cx - 0.5 * opts.width / scale, cy + 0.5 * opts.height / scale, opts.caption_height)


def follow_view(x: float, y: float, window: float, opts: RenderOptions) -> View:
    """A ``window``-metre square (across the map area's width) centred on (x, y)."""
    scale = opts.width / window
    return View(scale, x - 0.5 * opts.width / scale, y + 0.5 * opts.height / scale, opts.caption_height)


def _window(lanes: list[LaneLine], opts: RenderOptions) -> float:
    """0 for the whole network, else the side of the window that follows the ego."""
    if opts.window is not None:
        return opts.window
    x0, y0, x1, y1 = _bounds(lanes)
    return 0.0 if max(x1 - x0, y1 - y0) <= opts.fit_extent else opts.follow_window


def frame_view(recording: SceneRecording, frame: Frame, opts: RenderOptions, previous: View | None = None) -> View:
    """The view a frame is drawn in: the whole network, or the window around its ego (the
    ``previous`` view when the frame has no ego, e.g. after it left the network)."""
    window = _window(recording.lanes, opts)
    if window == 0.0:
        return network_view(recording.lanes, opts, () if recording.lanes else frame.vehicles)
    ego = frame.ego()
    if ego is None:
        return previous if previous is not None else network_view(recording.lanes, opts, frame.vehicles)
    return follow_view(ego.x, ego.y, window, opts)


def _corners(v: VehicleMarker, view: View) -> list[tuple[float, float]]:
    c, s = math.cos(v.yaw), math.sin(v.yaw)
    hl, hw = 0.5 * v.length, 0.5 * v.width
    return [view.project(v.x + dx * c - dy * s, v.y + dx * s + dy * c)
            for dx, dy in ((hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw))]  # fmt: skip


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError):  # Pillow built without FreeType: the fixed bitmap font
        return ImageFont.load_default()


@dataclass
class Caption:
    title: str
    episode: EpisodeFrames
    font: ImageFont.FreeTypeFont | ImageFont.ImageFont
    small: ImageFont.FreeTypeFont | ImageFont.ImageFont
    step_seconds: float


def draw_frame(lanes: list[LaneLine], frame: Frame, view: View, opts: RenderOptions,
               caption: Caption | None = None) -> Image.Image:  # fmt: skip
    """One frame: background, road, vehicles (ego last, outlined), caption band."""
    img = Image.new("RGB", (opts.width, opts.height + opts.caption_height), BACKGROUND)
    draw = ImageDraw.Draw(img)
    # the map area in world coordinates, with a lane's width to spare: lanes wholly outside are skipped
    x_lo, y_hi = view.x0, view.y1
    x_hi, y_lo = x_lo + opts.width / view.scale, y_hi - opts.height / view.scale
    for lane in lanes:
        pts = lane.points
        lo, hi = pts.min(axis=0) - lane.width, pts.max(axis=0) + lane.width
        if hi[0] < x_lo or lo[0] > x_hi or hi[1] < y_lo or lo[1] > y_hi:
            continue
        width = max(1, int(round(lane.width * view.scale)) - 2)  # a 2-pixel gap between lanes
        draw.line([view.project(float(x), float(y)) for x, y in pts], fill=ROAD, width=width, joint="curve")
    ego = None
    for v in frame.vehicles:
        if v.role == EGO_ROLE:
            ego = v
            continue
        draw.polygon(_corners(v, view), fill=ROLE_RGB.get(v.role, ROLE_RGB[TRAFFIC_ROLE]), outline=OUTLINE)
    if ego is not None:
        draw.polygon(_corners(ego, view), fill=ROLE_RGB[EGO_ROLE], outline=OUTLINE, width=2)
        if frame.vetoed is not None:  # the safety node refused a lane change here: a ring around the ego
            cx, cy = view.project(ego.x, ego.y)
            r = max(8.0, 0.75 * ego.length * view.scale)
            draw.ellipse((cx - r, cy - r, cx + r, cy + r), outline=VETO, width=3)
    if caption is not None and opts.caption_height:
        _draw_caption(draw, frame, opts, caption)
    return img


def caption_lines(title: str, ep: EpisodeFrames, frame: Frame, step_seconds: float) -> tuple[str, str]:
    """The caption of ``frame``: where (episode, step of how many, simulated time) and what (the action
    taken from here, the reward of arriving here, the return so far; the outcome once it is known, at
    the episode's last frame)."""
    n_steps = len(ep.frames) - 1
    line1 = f"{title}   episode {ep.label}   step {frame.step}/{n_steps}   t = {frame.step * step_seconds:.1f} s"
    action = "-" if frame.action is None else ACTION_NAMES[frame.action] if 0 <= frame.action < len(
        ACTION_NAMES) else str(frame.action)  # fmt: skip
    reward = "-" if frame.reward is None else f"{frame.reward:+.2f}"
    outcome = ep.summary.outcome if frame.step == n_steps else "..."
    line2 = f"action {action}   reward {reward}   return {frame.ret:+.2f}   outcome {outcome}"
    if frame.vetoed is not None:
        vetoed = ACTION_NAMES[frame.vetoed] if 0 <= frame.vetoed < len(ACTION_NAMES) else str(frame.vetoed)
        line2 += f"   VETOED {vetoed} (safety)"
    return line1, line2


def _draw_caption(draw: ImageDraw.ImageDraw, frame: Frame, opts: RenderOptions, cap: Caption) -> None:
    draw.rectangle((0, 0, opts.width, opts.caption_height - 1), fill=BAND)
    line1, line2 = caption_lines(cap.title, cap.episode, frame, cap.step_seconds)
    draw.text((8, 4), line1, fill=TEXT, font=cap.font)
    draw.text((8, 22), line2, fill=TEXT, font=cap.font)
    x = 8
    for role, rgb in ROLE_RGB.items():
        draw.rectangle((x, 46, x + 9, 55), fill=rgb)
        label = role.replace("_", " ")
        draw.text((x + 13, 44), label, fill=TEXT, font=cap.small)
        x += 13 + int(draw.textlength(label, font=cap.small)) + 10


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_bag` wrote."""

    path: Path
    frames: int
    episodes: list[str]
    seconds: float


def render_recording(recording: SceneRecording, out: str | Path, title: str = "",
                     opts: RenderOptions | None = None) -> int:  # fmt: skip
    """Draw every frame of ``recording`` and write the animation; returns the frames written."""
    opts = opts or RenderOptions()
    font, small = _font(14), _font(11)

    def frames():  # noqa: ANN202 - a generator: MP4 frames stream to the encoder
        for ep in recording.episodes:
            cap = Caption(title, ep, font, small, recording.step_seconds)
            view = None
            for frame in ep.frames:
                view = frame_view(recording, frame, opts, view)
                yield draw_frame(recording.lanes, frame, view, opts, cap)

    fps = opts.fps if opts.fps is not None else 2.0 / recording.step_seconds
    return write_animation(frames(), out, fps, palette=PALETTE)


def render_bag(bag: str | Path, out: str | Path, episode: int | None = None, span: tuple[int, int] | None = None,
               opts: RenderOptions | None = None, namespace: str | None = None) -> RenderResult:  # fmt: skip
    """Read the chosen episodes' scene from ``bag`` and write the animation ``out`` (.gif or .mp4)."""
    t0 = time.perf_counter()
    check_output(out)
    reader = BagReader(bag)
    recording = read_scene(reader, episode, span, namespace)
    n = render_recording(recording, out, reader.name, opts)
    return RenderResult(Path(out), n, [e.label for e in recording.episodes], time.perf_counter() - t0)
