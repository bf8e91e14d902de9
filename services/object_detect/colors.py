"""Colour statistics and colour files: seed 004's Balloon Color Picker (§4.3.2), pure numpy.

A selection of pixels (sRGB) is converted to HSV and to L*a*b* (OpenCV's 8-bit scales: H in
half degrees 0-179, S and V 0-255; L 0-255 for 0-100, a* and b* offset by 128). Per channel:
- the mean and the standard deviation (eq. 4.1-4.2); for the hue, an angle, the circular mean
  (eq. 4.3) and the circular standard deviation σ = sqrt(-2 ln R̄) with R̄ the length of the
  mean resultant vector. Eq. 4.4-4.6 print the sums of sines and cosines where the means belong
  (as printed, R = sqrt(s² + c²) grows with the number of pixels and the logarithm turns
  negative); the means are what the circular standard deviation is defined with.
- thresholds mean ± multiplier · σ (eq. 4.9-4.10); a hue interval may wrap around 0°.

Accumulating selections: eq. 4.7-4.8 do not pool. (m̄_o + m̄)/n is not the mean of both sets
unless n = 2 and both are the same size, and σ_o² + σ² + m̄_o + m̄ - 2m̄_n adds a variance to a
mean. The pooled figures come from the counts, sums and sums of squares (for the hue, the sums
of sines and cosines), which `ColorStats` carries: the mean and σ of all selected pixels at
once, whatever the order and sizes of the selections (a test shows the difference).

The 2D histogram LUT (§4.3.2, Fig. 4.8): the (H, S) or (a*, b*) histogram of the selected pixels,
cells with at least `min_count` pixels, grown by `grow` cells: any colour in a marked cell is the
object's, which follows a spread that is not a rectangle.
"""
from __future__ import annotations

import base64
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

HUE_UNITS = 180  # OpenCV's 8-bit hue: half degrees
SPACES = ("hsv", "lab")


def to_space(rgb: np.ndarray, space: str) -> np.ndarray:
    """(…, 3) uint8 sRGB → uint8 HSV or L*a*b* in OpenCV's 8-bit scales."""
    rgb = np.asarray(rgb, dtype=np.uint8)
    if rgb.size == 0:  # OpenCV refuses an empty image
        return np.zeros(np.shape(rgb), dtype=np.uint8)
    code = cv2.COLOR_RGB2HSV if space == "hsv" else cv2.COLOR_RGB2LAB
    if rgb.ndim == 3:  # an image as it is: OpenCV pays a set-up per row, a (N, 1, 3) column costs 8×
        return cv2.cvtColor(np.ascontiguousarray(rgb), code)
    return cv2.cvtColor(np.ascontiguousarray(rgb.reshape(-1, 1, 3)), code).reshape(np.shape(rgb))


@dataclass
class ChannelSums:
    """What pools: count, sum and sum of squares (linear channel) or of sines and cosines (hue)."""

    count: int = 0
    total: float = 0.0
    squares: float = 0.0
    sines: float = 0.0
    cosines: float = 0.0


@dataclass
class ColorStats:
    """Per space, per channel sums of every selection so far (§4.3.2 "accumulate the selected regions")."""

    sums: dict[str, list[ChannelSums]] = field(default_factory=lambda: {s: [ChannelSums() for _ in range(3)] for s in SPACES})
    pixels: dict[str, list[np.ndarray]] = field(default_factory=lambda: {s: [] for s in SPACES})

    def add(self, rgb: np.ndarray) -> None:
        """Accumulate a selection of sRGB pixels (…, 3)."""
        for space in SPACES:
            values = to_space(rgb, space).reshape(-1, 3).astype(np.float64)
            self.pixels[space].append(values.astype(np.uint8))
            for c in range(3):
                s, x = self.sums[space][c], values[:, c]
                s.count += len(x)
                s.total += float(x.sum())
                s.squares += float((x * x).sum())
                if space == "hsv" and c == 0:
                    angle = x * (2 * math.pi / HUE_UNITS)
                    s.sines += float(np.sin(angle).sum())
                    s.cosines += float(np.cos(angle).sum())

    @property
    def count(self) -> int:
        return self.sums["hsv"][0].count

    def mean_sigma(self, space: str) -> tuple[np.ndarray, np.ndarray]:
        """(mean, σ) per channel of all pixels so far: eq. 4.1-4.2 (σ with n - 1), the hue circular."""
        means, sigmas = np.zeros(3), np.zeros(3)
        for c, s in enumerate(self.sums[space]):
            if s.count == 0:
                raise ValueError("no pixels selected")
            if space == "hsv" and c == 0:
                means[c], sigmas[c] = circular_mean_sigma(s.sines / s.count, s.cosines / s.count)
            else:
                means[c] = s.total / s.count
                spread = max(s.squares - s.count * means[c] ** 2, 0.0)
                sigmas[c] = math.sqrt(spread / (s.count - 1)) if s.count > 1 else 0.0
        return means, sigmas


def circular_mean_sigma(mean_sine: float, mean_cosine: float) -> tuple[float, float]:
    """(mean, σ) in hue units (half degrees, 0 <= mean < 180) from the mean sine and cosine of the
    angles (eq. 4.3 and the circular standard deviation sqrt(-2 ln R̄))."""
    angle = math.atan2(mean_sine, mean_cosine) % (2 * math.pi)
    length = min(math.hypot(mean_sine, mean_cosine), 1.0)
    sigma = math.sqrt(-2.0 * math.log(length)) if length > 0 else math.inf
    scale = HUE_UNITS / (2 * math.pi)
    return angle * scale % HUE_UNITS, sigma * scale


def seed_pooled(mean_old: float, sigma_old: float, mean_new: float, sigma_new: float, n: int) -> tuple[float, float]:
    """Eq. 4.7-4.8 as printed (for the test that shows why they are not used)."""
    mean = (mean_old + mean_new) / n
    return mean, sigma_old ** 2 + sigma_new ** 2 + mean_old + mean_new - 2 * mean


@dataclass(frozen=True)
class Thresholds:
    """Eq. 4.9-4.10 per channel in OpenCV's 8-bit scale; a hue interval with lower > upper wraps."""

    space: str
    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    @classmethod
    def from_stats(cls, space: str, mean: np.ndarray, sigma: np.ndarray, multiplier) -> "Thresholds":
        k = np.broadcast_to(np.asarray(multiplier, dtype=np.float64), (3,))
        lower, upper = mean - sigma * k, mean + sigma * k
        if space == "hsv":
            if upper[0] - lower[0] >= HUE_UNITS:  # the whole circle
                lower[0], upper[0] = 0.0, HUE_UNITS - 1e-9
            else:
                lower[0], upper[0] = lower[0] % HUE_UNITS, upper[0] % HUE_UNITS
            channels = slice(1, 3)
        else:
            channels = slice(0, 3)
        lower[channels] = np.clip(lower[channels], 0, 255)
        upper[channels] = np.clip(upper[channels], 0, 255)
        return cls(space, tuple(float(v) for v in lower), tuple(float(v) for v in upper))

    def mask(self, values: np.ndarray) -> np.ndarray:
        """bool (…) of uint8 colour-space values (…, 3) inside the thresholds."""
        v = np.asarray(values)
        inside = np.ones(v.shape[:-1], dtype=bool)
        for c in range(3):
            lo, hi = self.lower[c], self.upper[c]
            if self.space == "hsv" and c == 0 and lo > hi:
                inside &= (v[..., c] >= lo) | (v[..., c] <= hi)
            else:
                inside &= (v[..., c] >= lo) & (v[..., c] <= hi)
        return inside

    def mask_image(self, values: np.ndarray) -> np.ndarray:
        """`mask` of an (H, W, 3) uint8 image, the same bits, by OpenCV's inRange (one pass per
        interval instead of six numpy passes): for integer v, v >= lo is v >= ceil(lo) and v <= hi
        is v <= floor(hi); bounds beyond 0-255 are clamped first (inRange would saturate them)."""
        values = np.ascontiguousarray(values, dtype=np.uint8)
        lower = [min(max(math.ceil(v), 0), 256) for v in self.lower]
        upper = [min(max(math.floor(v), -1), 255) for v in self.upper]
        if self.space == "hsv" and self.lower[0] > self.upper[0]:  # the hue wraps: two intervals
            hues = [(lower[0], 255), (0, upper[0])]
        else:
            hues = [(lower[0], upper[0])]
        inside = np.zeros(values.shape[:2], dtype=np.uint8)
        for low, high in hues:
            box = [(low, high), (lower[1], upper[1]), (lower[2], upper[2])]
            if all(a <= b for a, b in box):
                inside |= cv2.inRange(values, tuple(a for a, _ in box), tuple(b for _, b in box))
        return inside.astype(bool)


@dataclass(frozen=True)
class Lut:
    """The 2D histogram mask (§4.3.2): bool (256, 256) over the (H, S) or (a*, b*) bytes, with a
    range for the third channel (V or L)."""

    space: str
    mask: np.ndarray
    third: tuple[float, float]

    @classmethod
    def from_pixels(cls, space: str, values: np.ndarray, third: tuple[float, float], min_count: int = 2,
                    grow: int = 2) -> "Lut":
        v = np.asarray(values, dtype=np.uint8).reshape(-1, 3)
        first, second = (0, 1) if space == "hsv" else (1, 2)
        counts = np.zeros((256, 256), dtype=np.int64)
        np.add.at(counts, (v[:, first], v[:, second]), 1)
        marked = (counts >= min_count).astype(np.uint8)
        if grow > 0:
            kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
            marked = cv2.dilate(marked, kernel)
            if space == "hsv":  # the hue wraps: grow across 0 / 179 too
                wrapped = cv2.dilate(np.roll(marked, HUE_UNITS // 2, axis=0), kernel)
                marked |= np.roll(wrapped, -(HUE_UNITS // 2), axis=0)
                marked[HUE_UNITS:] = 0
        return cls(space, marked.astype(bool), (float(third[0]), float(third[1])))

    def lookup(self, values: np.ndarray) -> np.ndarray:
        v = np.asarray(values)
        first, second, other = (0, 1, 2) if self.space == "hsv" else (1, 2, 0)
        inside = self.mask[v[..., first], v[..., second]]
        return inside & (v[..., other] >= self.third[0]) & (v[..., other] <= self.third[1])

    def encoded(self) -> str:
        return base64.b64encode(np.packbits(self.mask).tobytes()).decode("ascii")

    @classmethod
    def decoded(cls, space: str, text: str, third) -> "Lut":
        bits = np.unpackbits(np.frombuffer(base64.b64decode(text.encode("ascii"), validate=True), dtype=np.uint8))
        if len(bits) != 256 * 256:
            raise ValueError(f"a LUT mask holds {256 * 256} bits, this one {len(bits)}")
        return cls(space, bits.reshape(256, 256).astype(bool), (float(third[0]), float(third[1])))


@dataclass(frozen=True)
class ColorFile:
    """What Object Detect segments with: thresholds, or a LUT, in one colour space, and the
    object's diameter (its distance from its size in the image)."""

    name: str
    diameter: float  # m
    method: str  # "thresholds" | "lut"
    thresholds: Thresholds
    lut: Lut | None = None
    pixels: int = 0  # how many pixels the statistics came from

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        """bool (H, W) of the pixels of the object's colour."""
        values = to_space(rgb, self.thresholds.space)
        if self.method == "lut" and self.lut is not None:
            return self.lut.lookup(values)
        if values.ndim == 3 and values.size:
            return self.thresholds.mask_image(values)
        return self.thresholds.mask(values)

    def to_toml(self) -> str:
        t = self.thresholds
        lines = [
            "# Falconry colour file (falconry colors pick): what Object Detect segments as the object.",
            f'name = "{self.name}"',
            f"diameter = {self.diameter:g}  # m",
            f'method = "{self.method}"  # "thresholds" (eq. 4.9-4.10) or "lut" (2D histogram mask)',
            f"pixels = {self.pixels}",
            "",
            "[thresholds]  # OpenCV 8-bit scales (HSV: hue in half degrees, a hue with lower > upper wraps)",
            f'space = "{t.space}"',
            f"lower = [{', '.join(f'{v:.3f}' for v in t.lower)}]",
            f"upper = [{', '.join(f'{v:.3f}' for v in t.upper)}]",
        ]
        if self.lut is not None:
            lines += ["", "[lut]", f'space = "{self.lut.space}"',
                      f"third = [{self.lut.third[0]:.3f}, {self.lut.third[1]:.3f}]  # V (hsv) or L (lab) range",
                      f'mask = "{self.lut.encoded()}"']
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_toml(), encoding="utf-8")


class ColorFileError(ValueError):
    """A colour file that cannot be used; the message is one line naming the file."""


def load_color_file(path: str | Path) -> ColorFile:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ColorFileError(f"colour file not found: {path}") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ColorFileError(f"{path}: not a colour file: {' '.join(str(exc).split())}") from None
    return parse_color_file(data, str(path))


def parse_color_file(data: dict, source: str) -> ColorFile:
    try:
        t = data["thresholds"]
        space = str(t.get("space", "hsv"))
        if space not in SPACES:
            raise ValueError(f"thresholds.space must be one of {', '.join(SPACES)}, got {space!r}")
        lower, upper = _triple(t["lower"], "thresholds.lower"), _triple(t["upper"], "thresholds.upper")
        diameter = float(data["diameter"])
        if not 0 < diameter < 100:
            raise ValueError(f"diameter must be positive metres, got {diameter}")
        method = str(data.get("method", "thresholds"))
        lut = None
        if method == "lut":
            table = data["lut"]
            lut_space = str(table.get("space", space))
            if lut_space not in SPACES:
                raise ValueError(f"lut.space must be one of {', '.join(SPACES)}, got {lut_space!r}")
            lut = Lut.decoded(lut_space, str(table["mask"]), _pair(table.get("third", [0, 255]), "lut.third"))
        elif method != "thresholds":
            raise ValueError(f'method must be "thresholds" or "lut", got {method!r}')
        return ColorFile(str(data.get("name", "")), diameter, method, Thresholds(space, lower, upper), lut,
                         int(data.get("pixels", 0)))
    except KeyError as exc:
        raise ColorFileError(f"{source}: missing field {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ColorFileError(f"{source}: {' '.join(str(exc).split())}") from None


def _triple(value, name: str) -> tuple[float, float, float]:
    v = [float(x) for x in value]
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise ValueError(f"{name} must be three finite numbers")
    return (v[0], v[1], v[2])


def _pair(value, name: str) -> tuple[float, float]:
    v = [float(x) for x in value]
    if len(v) != 2:
        raise ValueError(f"{name} must be two numbers")
    return (v[0], v[1])
