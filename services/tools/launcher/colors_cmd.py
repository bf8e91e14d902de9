"""`falconry colors` (seed 004 §4.3, the Balloon Color Picker without its GUI) and `falconry snapshot`.

- `falconry colors pick SOURCE --roi x,y,w,h [--roi ...]`: the pixels of the regions (an image
  file, or a frame of a recording's compressed camera stream) pooled into colour statistics, the
  thresholds of eq. 4.9-4.10 (or a 2D histogram LUT) written to a colour file Object Detect loads
  (its `colors` parameter), optionally sent live to a running Object Detect (`--send`). With
  `--append FILE` the regions join that file's statistics (the file keeps the pooled sums).
- `falconry colors show SOURCE --colors FILE --out PNG`: the image beside its segmentation.
- `falconry snapshot --uav UAV --out PNG`: the next frame of a running camera.
"""
from __future__ import annotations

import argparse
import time
import tomllib
from pathlib import Path

import cv2
import msgspec
import numpy as np

from schemas import keys
from schemas.messages import CameraFrame, ColorUpdate, CompressedFrame, Header
from schemas.arrays import to_numpy
from services.tools.launcher.common import CliError, add_zenoh_options, zenoh_settings
from services.object_detect.colors import (
    SPACES,
    ChannelSums,
    ColorFile,
    ColorFileError,
    ColorStats,
    Lut,
    Thresholds,
    load_color_file,
)
from services.lib.runtime.zenoh_config import init_logging, open_session


def parse_roi(text: str) -> tuple[int, int, int, int]:
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give x,y,w,h in pixels, e.g. 300,90,20,20") from None
    if w <= 0 or h <= 0 or x < 0 or y < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: x and y must be >= 0, w and h > 0")
    return x, y, w, h


def add_parser(commands) -> None:
    p = commands.add_parser("colors", help="pick an object's colours from images (seed 004's Balloon Color Picker)",
                            description="Colour files for Object Detect. `falconry colors pick --help`.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    pick = actions.add_parser(
        "pick", help="colour statistics of image regions into a colour file",
        description="Pool the pixels of the regions into per-channel statistics in HSV and L*a*b* (the hue's "
                    "circular), write thresholds mean ± multiplier·σ (seed 004 eq. 4.9-4.10) or a 2D histogram "
                    "LUT to a colour file Object Detect loads. SOURCE is an image (PNG, JPEG) or a recording "
                    "(.mcap) with the camera's compressed frames (falconry/<uav>/camera_jpeg).")
    _add_source(pick)
    pick.add_argument("--roi", type=parse_roi, action="append", required=True, metavar="x,y,w,h",
                      help="a region of the object, pixels (repeat for several)")
    pick.add_argument("--space", choices=SPACES, default="hsv", help="colour space to segment in (default hsv)")
    pick.add_argument("--method", choices=["thresholds", "lut"], default="thresholds",
                      help="thresholds per channel (eq. 4.9-4.10) or the 2D histogram mask (default thresholds)")
    pick.add_argument("--multiplier", type=float, nargs="+", default=[3.0], metavar="K",
                      help="σ multiplier per channel, one value or three (default 3)")
    pick.add_argument("--diameter", type=float, default=0.6, metavar="M", help="the object's diameter (default 0.6)")
    pick.add_argument("--name", default="", help="the colour's name (default: the output file's stem)")
    pick.add_argument("--out", metavar="FILE", help="colour file to write (default: the --append file, else colors.toml)")
    pick.add_argument("--append", metavar="FILE", help="pool with the statistics of this colour file")
    pick.add_argument("--send", action="store_true", help="also send the colours to the running Object Detect of --uav")
    add_zenoh_options(pick, "With --send give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=0)
    pick.set_defaults(handler=run_pick)

    show = actions.add_parser("show", help="write an image beside its segmentation by a colour file as PNG",
                              description="The image (or a recording's frame) and, beside it, the pixels the colour "
                                          "file segments, in white.")
    _add_source(show)
    show.add_argument("--colors", required=True, metavar="FILE", help="colour file (or a built-in name: red, green)")
    show.add_argument("--out", required=True, metavar="PNG", help="where to write the picture")
    show.set_defaults(handler=run_show)

    snap = commands.add_parser("snapshot", help="save the next frame of a running camera as PNG",
                               description="Wait for the next frame on falconry/<uav>/camera and write it as PNG "
                                           "(and its depth image, 16-bit mm, beside it with --depth).")
    snap.add_argument("--uav", default="uav1", help="whose camera (default uav1)")
    snap.add_argument("--out", required=True, metavar="PNG", help="where to write the frame")
    snap.add_argument("--depth", metavar="PNG", help="also write the depth image (16-bit, mm) here")
    snap.add_argument("--timeout", type=float, default=5.0, metavar="S", help="how long to wait (default 5)")
    add_zenoh_options(snap, "Give the run's hub, e.g. --connect tcp/127.0.0.1:PORT.", connect_timeout=0)
    snap.set_defaults(handler=run_snapshot)


# ------------------------------------------------------------------ sources
def _add_source(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE", help="image file or .mcap recording")
    parser.add_argument("--frame", type=int, default=0, metavar="K", help="recording: the K-th frame (default 0)")
    parser.add_argument("--uav", default="uav1", help="recording: whose camera (default uav1)")


def read_source(source: str, frame: int, uav: str) -> np.ndarray:
    """uint8 (H, W, 3) RGB of an image file or of a recording's K-th compressed camera frame."""
    path = Path(source)
    if not path.is_file():
        raise CliError(f"no such file: {source}")
    if path.suffix.lower() == ".mcap":
        return _recording_frame(path, frame, uav)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise CliError(f"{source}: not an image OpenCV can read")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _recording_frame(path: Path, frame: int, uav: str) -> np.ndarray:
    from services.tools.recorder.mcap_io import read_recording

    key = keys.uav(uav, "camera_jpeg")
    decoder = msgspec.msgpack.Decoder(CompressedFrame)
    seen = 0
    try:
        for message in read_recording(str(path), lambda k: k == key):
            if seen == frame:
                image = cv2.imdecode(np.frombuffer(decoder.decode(message.payload).jpeg, np.uint8), cv2.IMREAD_COLOR)
                if image is None:
                    raise CliError(f"{path}: frame {frame} of {key} is not a JPEG")
                return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
            seen += 1
    except (OSError, ValueError, msgspec.DecodeError) as exc:
        raise CliError(f"{path}: cannot read the recording: {' '.join(str(exc).split())}") from None
    raise CliError(f"{path}: {seen} frames on {key}, no frame {frame}")


def regions(rgb: np.ndarray, rois: list[tuple[int, int, int, int]]) -> list[np.ndarray]:
    height, width = rgb.shape[:2]
    out = []
    for x, y, w, h in rois:
        if x + w > width or y + h > height:
            raise CliError(f"region {x},{y},{w},{h} reaches outside the {width} × {height} image")
        out.append(rgb[y:y + h, x:x + w].reshape(-1, 3))
    return out


# ------------------------------------------------------------------ pick
def run_pick(args: argparse.Namespace) -> int:
    if len(args.multiplier) not in (1, 3) or min(args.multiplier) <= 0:
        raise CliError("--multiplier takes one or three positive numbers")
    if not args.diameter > 0:
        raise CliError("--diameter must be positive")
    stats = _stats_of(args.append) if args.append else ColorStats()
    rgb = read_source(args.source, args.frame, args.uav)
    for pixels in regions(rgb, args.roi):
        stats.add(pixels)
    out = Path(args.out or args.append or "colors.toml")
    name = args.name or out.stem
    mean, sigma = stats.mean_sigma(args.space)
    thresholds = Thresholds.from_stats(args.space, mean, sigma, args.multiplier)
    lut = None
    if args.method == "lut":
        values = np.concatenate(stats.pixels[args.space]) if stats.pixels[args.space] else np.zeros((0, 3), np.uint8)
        third = (thresholds.lower[2], thresholds.upper[2]) if args.space == "hsv" else (thresholds.lower[0],
                                                                                          thresholds.upper[0])
        lut = Lut.from_pixels(args.space, values, third)
    colors = ColorFile(name, args.diameter, args.method, thresholds, lut, stats.count)
    out.write_text(colors.to_toml() + _stats_toml(stats), encoding="utf-8")
    hsv_mean, hsv_sigma = stats.mean_sigma("hsv")
    lab_mean, lab_sigma = stats.mean_sigma("lab")
    print(f"{stats.count} pixels from {len(args.roi)} region(s)"
          + (f" pooled with {args.append}" if args.append else ""))
    print(f"  HSV  mean H {hsv_mean[0] * 2:.1f}° S {hsv_mean[1]:.1f} V {hsv_mean[2]:.1f}   "
          f"σ H {hsv_sigma[0] * 2:.2f}° S {hsv_sigma[1]:.2f} V {hsv_sigma[2]:.2f}")
    print(f"  Lab  mean L {lab_mean[0]:.1f} a {lab_mean[1]:.1f} b {lab_mean[2]:.1f}   "
          f"σ L {lab_sigma[0]:.2f} a {lab_sigma[1]:.2f} b {lab_sigma[2]:.2f}   (OpenCV 8-bit scales)")
    print(f"  {args.space} thresholds lower {_fmt(thresholds.lower)} upper {_fmt(thresholds.upper)}"
          + (" (the hue wraps)" if args.space == "hsv" and thresholds.lower[0] > thresholds.upper[0] else ""))
    print(f"wrote {out} ({args.method}, diameter {args.diameter:g} m)")
    if args.send:
        _send(args, colors, out)
    return 0


def _fmt(values) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in values) + "]"


def _stats_toml(stats: ColorStats) -> str:
    """The pooled sums, so a later `--append` pools exactly (not part of what Object Detect reads)."""
    lines = ["", "[stats]  # pooled sums per channel: count, sum, sum of squares, sum of sines, sum of cosines"]
    for space in SPACES:
        rows = [[s.count, s.total, s.squares, s.sines, s.cosines] for s in stats.sums[space]]
        lines.append(f"{space} = {rows!r}")
    return "\n".join(lines) + "\n"


def _stats_of(path: str) -> ColorStats:
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
        table = data["stats"]
        stats = ColorStats()
        for space in SPACES:
            rows = table[space]
            if len(rows) != 3 or any(len(r) != 5 for r in rows):
                raise ValueError(f"stats.{space} needs three rows of five numbers")
            stats.sums[space] = [ChannelSums(int(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]))
                                 for r in rows]
        return stats
    except FileNotFoundError:
        raise CliError(f"--append: no such file: {path}") from None
    except (KeyError, TypeError, ValueError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CliError(f"--append {path}: not a colour file written by `falconry colors pick` ({exc})") from None


def _send(args: argparse.Namespace, colors: ColorFile, path: Path) -> None:
    if args.zenoh_profile == "embedded" and not args.connect and not args.zenoh_config:
        raise CliError("--send: give the run with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    init_logging()
    session = open_session(zenoh_settings(args))
    try:
        key = keys.uav(args.uav, keys.COLORS)
        publisher = session.declare_publisher(key)
        time.sleep(0.3)  # let the subscription reach us before the one message
        publisher.put(msgspec.msgpack.encode(ColorUpdate(header=Header(sender="ground/colors", seq=1),
                                                         name=colors.name, toml=path.read_text(encoding="utf-8"))))
        time.sleep(0.2)
        publisher.undeclare()
    finally:
        session.close()
    print(f"sent to {key}")


# ------------------------------------------------------------------ show
def run_show(args: argparse.Namespace) -> int:
    from services.object_detect.node import color_file_path

    try:
        colors = load_color_file(color_file_path(args.colors))
    except ColorFileError as exc:
        raise CliError(str(exc)) from None
    rgb = read_source(args.source, args.frame, args.uav)
    mask = colors.segment(rgb)
    picture = np.concatenate([rgb, np.repeat((mask * 255).astype(np.uint8)[..., None], 3, axis=2)], axis=1)
    if not cv2.imwrite(args.out, cv2.cvtColor(picture, cv2.COLOR_RGB2BGR)):
        raise CliError(f"cannot write {args.out}")
    print(f"{int(mask.sum())} of {mask.size} pixels are {colors.name or 'the colour'} ({100 * mask.mean():.2f} %); "
          f"wrote {args.out}")
    return 0


# ------------------------------------------------------------------ snapshot
def run_snapshot(args: argparse.Namespace) -> int:
    if args.zenoh_profile == "embedded" and not args.connect and not args.zenoh_config:
        raise CliError("give the run with --connect ENDPOINT (e.g. tcp/127.0.0.1:PORT)")
    init_logging()
    session = open_session(zenoh_settings(args))
    got: list[bytes] = []
    try:
        subscriber = session.declare_subscriber(keys.uav(args.uav, "camera"),
                                                lambda sample: got.append(sample.payload.to_bytes()) if not got else None)
        deadline = time.monotonic() + args.timeout
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        subscriber.undeclare()
    finally:
        session.close()
    if not got:
        print(f"no frame on {keys.uav(args.uav, 'camera')} within {args.timeout:g} s")
        return 1
    frame = msgspec.msgpack.decode(got[0], type=CameraFrame)
    rgb = to_numpy(frame.color)
    if not cv2.imwrite(args.out, cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)):
        raise CliError(f"cannot write {args.out}")
    print(f"{frame.width} × {frame.height} frame of t={frame.header.stamp / 1e9:.2f} s to {args.out}")
    if args.depth and frame.depth is not None:
        cv2.imwrite(args.depth, np.ascontiguousarray(to_numpy(frame.depth)))
        print(f"depth (16-bit, mm) to {args.depth}")
    return 0
