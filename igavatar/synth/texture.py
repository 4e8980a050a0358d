"""A procedural solid texture of the clothed subject, evaluated at canonical-space points.

    texture = make_texture("stripes", seed=0, landmarks=find_landmarks(x_rest, weights, names, joints_rest))
    albedo = texture.albedo(x_canonical, region_ids(coverage))      # (P, 3) RGB in [0, 1]

Because color is a function of the canonical position only, a point keeps its color in every
frame and view. Details are deliberately high-frequency (2 cm stripes, 3 cm checks, printed letters,
eyes and mouth) so that a reconstruction has to resolve them and the subject's facing is visible.
Shapes: P points, V vertices, C coverage channels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from igavatar.errors import BodyModelError, InputError
from igavatar.synth.garments import COVERAGE_CHANNELS, REGION_PRIORITY, REGIONS

TextureStyle = Literal["stripes", "checker", "plain", "bold"]
TEXTURES: tuple[str, ...] = get_args(TextureStyle)

SKIN_TONES = np.array(
    [[0.96, 0.80, 0.69], [0.91, 0.72, 0.58], [0.80, 0.60, 0.45], [0.62, 0.44, 0.32], [0.45, 0.30, 0.22]]
)
GARMENT_COLORS = np.array(
    [[0.80, 0.12, 0.12], [0.12, 0.32, 0.75], [0.10, 0.55, 0.25], [0.90, 0.62, 0.10], [0.45, 0.18, 0.60],
     [0.05, 0.55, 0.62], [0.85, 0.40, 0.55], [0.92, 0.90, 0.85]]
)
TROUSER_COLORS = np.array(
    [[0.15, 0.20, 0.35], [0.25, 0.25, 0.27], [0.40, 0.30, 0.20], [0.55, 0.50, 0.40], [0.10, 0.10, 0.12]]
)
HAIR_COLORS = np.array([[0.10, 0.07, 0.05], [0.30, 0.18, 0.08], [0.55, 0.38, 0.18], [0.80, 0.65, 0.40]])
SHOE_COLOR = np.array([0.08, 0.08, 0.09])


def region_ids(coverage: np.ndarray) -> np.ndarray:
    """(P,) int region index into REGIONS from (P, C) coverages: the outermost garment covering > 0.5."""
    regions = np.zeros(coverage.shape[0], dtype=np.int64)
    for name in reversed(REGION_PRIORITY):
        channel = COVERAGE_CHANNELS.index(name)
        regions = np.where(coverage[:, channel] > 0.5, REGIONS.index(name), regions)
    return regions


@dataclass(frozen=True)
class TextureLandmarks:
    """Canonical-space anchors of the face features and the chest print (meters).

    Attributes:
        eyes: (2, 3) eyeball centers (left, right).
        mouth: (3,) front-most point of the lips.
        chest: (3,) center of the chest print, on the torso's front.
        legs: (2, 2, 3) hip and ankle joint of the left and right leg (trouser stripes run along them).
        body_scale: standing height over 1.65 m; feature sizes (eyes, print) scale with it.
    """

    eyes: np.ndarray
    mouth: np.ndarray
    chest: np.ndarray
    legs: np.ndarray
    body_scale: float


def find_landmarks(
    x_rest: np.ndarray, weights: np.ndarray, bone_names: Sequence[str], joints_rest: np.ndarray
) -> TextureLandmarks:
    """Locate the eyes, mouth, chest and legs on a rest-pose Anny body (+Z up, face towards -Y).

    Args:
        x_rest: (V, 3) rest vertices including Anny's eyeball shells.
        weights: (V, J) skinning weights; eyeball vertices are the ones bound to 'eye.L' / 'eye.R'.
        bone_names: the J bone names.
        joints_rest: (J, 3) rest bone heads.
    """
    names = list(bone_names)
    legs = []
    for side in ("L", "R"):
        for bone in (f"upperleg01.{side}", f"foot.{side}"):
            if bone not in names:
                raise BodyModelError(f"texture: bone '{bone}' not in the skeleton; trouser stripes need Anny's legs")
        legs.append([joints_rest[names.index(f"upperleg01.{side}")], joints_rest[names.index(f"foot.{side}")]])
    legs = np.asarray(legs, dtype=np.float64)
    eyes = []
    for side in ("L", "R"):
        if f"eye.{side}" not in names:
            raise BodyModelError(f"texture: bone 'eye.{side}' not in the skeleton; face features need Anny's eyes")
        bound = weights[:, names.index(f"eye.{side}")] > 0.5
        if not bound.any():
            raise BodyModelError(f"texture: no vertex is bound to 'eye.{side}'; face features need Anny's eyes")
        eyes.append(x_rest[bound].mean(axis=0))
    eyes = np.stack(eyes)
    eye_mid = eyes.mean(axis=0)
    height = float(np.ptp(x_rest[:, 2]))
    # Lips: the front-most midline point 3.3-5.2% of the body height below the eyes (under the nose).
    midline = np.abs(x_rest[:, 0] - eye_mid[0]) < 0.004 * height
    band = (x_rest[:, 2] < eye_mid[2] - 0.033 * height) & (x_rest[:, 2] > eye_mid[2] - 0.052 * height)
    candidates = x_rest[midline & band]
    if candidates.shape[0] == 0:
        raise BodyModelError("texture: found no lip vertices below the eyes; is this an Anny body?")
    mouth = candidates[np.argmin(candidates[:, 1])]
    # Chest print: centerd 0.22 body heights below the eyes, in front of the torso's midline.
    chest_z = eye_mid[2] - 0.22 * height
    torso = (np.abs(x_rest[:, 0] - eye_mid[0]) < 0.03 * height) & (np.abs(x_rest[:, 2] - chest_z) < 0.01 * height)
    chest_y = x_rest[torso, 1].min() if torso.any() else eye_mid[1]
    chest = np.array([eye_mid[0], chest_y, chest_z])
    return TextureLandmarks(eyes=eyes, mouth=mouth, chest=chest, legs=legs, body_scale=height / 1.65)


def _render_letters(text: str) -> np.ndarray:
    """(h, w) float32 in [0, 1]: `text` drawn white on black with OpenCV's Hershey font."""
    font, font_scale, thickness = cv2.FONT_HERSHEY_DUPLEX, 2.0, 5
    (width, height), baseline = cv2.getTextSize(text, font, font_scale, thickness)
    pad = 6
    image = np.zeros((height + baseline + 2 * pad, width + 2 * pad), dtype=np.uint8)
    cv2.putText(image, text, (pad, pad + height), font, font_scale, 255, thickness, cv2.LINE_AA)
    return image.astype(np.float32) / 255.0


def _smooth_square(phase: np.ndarray, duty: float = 0.5, softness: float = 0.06) -> np.ndarray:
    """Square wave in [0, 1] of a phase measured in periods, with edges softened over `softness` of a period."""
    frac = phase - np.floor(phase)
    rise = np.clip(frac / softness + 0.5, 0.0, 1.0)
    fall = np.clip((duty - frac) / softness + 0.5, 0.0, 1.0)
    wrap = np.clip((frac - 1.0) / softness + 0.5, 0.0, 1.0)
    return np.clip(np.minimum(rise, fall) + wrap, 0.0, 1.0)


@dataclass(frozen=True)
class SolidTexture:
    """Colors and patterns per region, as a function of canonical position.

    Attributes:
        style: one of TEXTURES.
        colors: region name -> (3,) base RGB in [0, 1].
        accents: region name -> (3,) second RGB of the pattern in that region.
        stripe_period: shirt stripe period in meters.
        check_size: trouser / plaid check size in meters.
        letters: (h, w) float32 print mask in [0, 1] projected onto the chest (empty for 'plain').
        text: the printed text.
        print_half_width: half width of the print in meters (for a 1.65 m subject).
        pinstripes: number of trouser pinstripes around each leg ('stripes' style).
        landmarks: where the face features and the print sit.
    """

    style: str
    colors: dict[str, np.ndarray]
    accents: dict[str, np.ndarray]
    stripe_period: float
    check_size: float
    letters: np.ndarray
    text: str
    landmarks: TextureLandmarks
    print_half_width: float = 0.08
    pinstripes: int = 18

    def albedo(self, x_canonical: np.ndarray, regions: np.ndarray) -> np.ndarray:
        """Surface color at canonical points.

        Args:
            x_canonical: (P, 3) canonical positions in meters.
            regions: (P,) region indices into REGIONS (see `region_ids`).
        Returns:
            (P, 3) float64 RGB in [0, 1].
        """
        x_canonical = np.asarray(x_canonical, dtype=np.float64)
        out = np.zeros((x_canonical.shape[0], 3))
        for r, name in enumerate(REGIONS):
            sel = regions == r
            if not sel.any():
                continue
            points = x_canonical[sel]
            base = np.broadcast_to(self.colors[name], points.shape)
            pattern = self._pattern(name, points)  # (p,) weight of the accent color
            color = base + pattern[:, None] * (self.accents[name] - base)
            if name == "skin":
                color = self._face(points, color)
            elif name == "top" and self.letters.size:
                color = self._print(points, color)
            out[sel] = color
        return np.clip(out, 0.0, 1.0)

    def _pattern(self, region: str, x: np.ndarray) -> np.ndarray:
        p, c = self.stripe_period, self.check_size
        if region == "hair":
            # Fine strands in both styles with texture: a weak high-frequency streak pattern.
            return 0.35 * _smooth_square((x[:, 0] * 3.0 + x[:, 1] * 1.7) / 0.006, duty=0.4, softness=0.3)
        if self.style == "plain":
            return np.zeros(x.shape[0])
        if region == "top":
            if self.style in ("stripes", "bold"):
                return _smooth_square(x[:, 2] / p, duty=0.45)
            # Plaid: two stripe families (height and around the body), overlapping darker.
            horizontal = _smooth_square(x[:, 2] / c, duty=0.3)
            vertical = _smooth_square((x[:, 0] + x[:, 1]) / c, duty=0.3)
            return np.clip(0.6 * horizontal + 0.6 * vertical, 0.0, 1.0)
        if region == "bottom":
            if self.style == "stripes":
                # Pinstripes running down each leg: a whole number of them around the leg's axis.
                return 0.7 * _smooth_square(self._leg_azimuth(x) * self.pinstripes, duty=0.2, softness=0.1)
            parity = (np.floor(x[:, 0] / c) + np.floor(x[:, 1] / c) + np.floor(x[:, 2] / c)) % 2
            return parity
        if region == "shoes":
            return 0.5 * _smooth_square(x[:, 2] / 0.01, duty=0.2)  # sole-like ridges
        return np.zeros(x.shape[0])

    def _leg_azimuth(self, x: np.ndarray) -> np.ndarray:
        """(P,) angle around the nearer leg's hip-ankle axis, in turns (0..1)."""
        best_distance = np.full(x.shape[0], np.inf)
        azimuth = np.zeros(x.shape[0])
        for hip, ankle in self.landmarks.legs:
            axis = (ankle - hip) / np.linalg.norm(ankle - hip)
            along = (x - hip) @ axis
            radial = x - hip - along[:, None] * axis
            distance = np.linalg.norm(radial, axis=1)
            # Two directions orthogonal to the axis: sideways (+X) and the remaining one.
            side = np.array([1.0, 0.0, 0.0]) - axis[0] * axis
            side /= np.linalg.norm(side)
            other = np.cross(axis, side)
            turns = np.arctan2(radial @ other, radial @ side) / (2.0 * np.pi)
            nearer = distance < best_distance
            azimuth = np.where(nearer, turns, azimuth)
            best_distance = np.minimum(distance, best_distance)
        return azimuth - np.floor(azimuth)

    def _face(self, x: np.ndarray, color: np.ndarray) -> np.ndarray:
        lm = self.landmarks
        scale = lm.body_scale
        color = color.copy()
        for eye in lm.eyes:
            d = (x - eye) / scale
            # The eyeball shells are dropped, so the sclera is painted into the socket behind them too.
            front = (d[:, 1] < 0.03) & (np.linalg.norm(d, axis=1) < 0.03)
            # Sclera (white, wide ellipse), iris (dark disc), brow (dark bar above).
            r_sclera = np.sqrt((d[:, 0] / 0.015) ** 2 + (d[:, 2] / 0.008) ** 2)
            r_iris = np.sqrt(d[:, 0] ** 2 + d[:, 2] ** 2) / 0.0065
            brow = (np.abs(d[:, 0]) < 0.018) & (np.abs(d[:, 2] - 0.019) < 0.0035) & (d[:, 1] < 0.02)
            color[front & (r_sclera < 1)] = [0.95, 0.95, 0.93]
            color[front & (r_iris < 1)] = [0.12, 0.20, 0.30]
            color[front & (r_iris < 0.45)] = [0.02, 0.02, 0.02]
            color[brow] = self.colors["hair"] * 0.8
        d = (x - lm.mouth) / scale
        lips = (np.sqrt((d[:, 0] / 0.024) ** 2 + (d[:, 2] / 0.008) ** 2) < 1) & (d[:, 1] < 0.02)
        color[lips] = [0.62, 0.22, 0.22]
        return color

    def _print(self, x: np.ndarray, color: np.ndarray) -> np.ndarray:
        lm = self.landmarks
        h, w = self.letters.shape
        half_width = self.print_half_width * lm.body_scale
        half_height = half_width * h / w
        # Planar projection along +Y onto the chest, only on the front half of the torso.
        u = (x[:, 0] - lm.chest[0]) / half_width  # -1..1 left to right as seen from the front
        v = (lm.chest[2] - x[:, 2]) / half_height  # -1..1 top to bottom
        inside = (np.abs(u) <= 1) & (np.abs(v) <= 1) & (x[:, 1] < lm.chest[1] + 0.08 * lm.body_scale)
        if not inside.any():
            return color
        rows = (v[inside] + 1) * 0.5 * (h - 1)
        cols = (u[inside] + 1) * 0.5 * (w - 1)
        alpha = map_coordinates(self.letters, [rows, cols], order=1, mode="constant")
        color = color.copy()
        color[inside] += alpha[:, None] * (self.accents["print"] - color[inside])
        return color


def make_texture(style: str, seed: int, landmarks: TextureLandmarks) -> SolidTexture:
    """Draw colors and the printed text from `seed` and build the texture of a style in TEXTURES."""
    if style not in TEXTURES:
        raise InputError(f"texture '{style}' is not known; choose one of {', '.join(TEXTURES)}")
    rng = np.random.default_rng(seed)
    skin = SKIN_TONES[rng.integers(len(SKIN_TONES))]
    top_index, accent_index = rng.choice(len(GARMENT_COLORS), size=2, replace=False)
    top = GARMENT_COLORS[top_index]
    top_accent = GARMENT_COLORS[accent_index]
    bottom = TROUSER_COLORS[rng.integers(len(TROUSER_COLORS))]
    bottom_accent = np.clip(bottom * 0.5 + 0.45, 0, 1) if style == "stripes" else np.clip(1.0 - bottom * 0.7, 0, 1)
    hair = HAIR_COLORS[rng.integers(len(HAIR_COLORS))]
    # Print in white or black, whichever contrasts more with both shirt colors.
    print_color = np.ones(3) if (top.mean() + top_accent.mean()) < 1.1 else np.zeros(3)
    letters_pool = "ABCDEFGHJKLMNPRSTUVWXYZ"
    text = "".join(rng.choice(list(letters_pool), size=3)) + str(int(rng.integers(10)))
    colors = {"skin": skin, "top": top, "bottom": bottom, "hair": hair, "shoes": SHOE_COLOR}
    accents = {
        "skin": skin, "top": top_accent, "bottom": bottom_accent, "hair": hair * 0.6,
        "shoes": np.array([0.3, 0.3, 0.3]), "print": print_color,
    }
    letters = _render_letters(text) if style != "plain" else np.zeros((0, 0), np.float32)
    if style == "bold":
        # The pattern that carved the surface in issue 36: 3 cm dark-green stripes on a white shirt
        # and a green checker on the shorts, the highest contrast a garment has.
        colors = colors | {"top": np.array([0.95, 0.95, 0.93]), "bottom": np.array([0.92, 0.92, 0.88])}
        accents = accents | {"top": np.array([0.08, 0.32, 0.14]), "bottom": np.array([0.1, 0.45, 0.2])}
        return SolidTexture(style=style, colors=colors, accents=accents, stripe_period=0.06, check_size=0.04,
                            letters=letters, text=text, landmarks=landmarks)
    return SolidTexture(
        style=style, colors=colors, accents=accents, stripe_period=0.02 + 0.005 * rng.random(),
        check_size=0.03, letters=letters, text=text, landmarks=landmarks,
    )
