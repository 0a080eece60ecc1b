"""Type hints of the package flashmat (docs/PYTHON.md)."""
from os import PathLike
from typing import Optional, Sequence, Union

import numpy
import torch

TORCH_VERSION: str
NMAT_VERSION: int
OVERHEAD: tuple[float, float, float]
__version__: str

Position = Union[Sequence[float], torch.Tensor]
Positions = Union[Position, Sequence[Sequence[float]]]
Device = Union[str, torch.device]
Path = Union[str, PathLike]

class Model:
    """A flashmat model (M_est with its neural BRDF) that turns flash photos into materials."""

    @property
    def path(self) -> str: ...
    @property
    def model_id(self) -> str: ...
    @property
    def device(self) -> str: ...
    def estimate(
        self,
        photo: Union[Path, torch.Tensor, numpy.ndarray],
        *,
        fov: Optional[float] = None,
        size: int = 256,
        exposure_mode: str = "calibrated",
        encoding: Optional[str] = None,
        exposure: Optional[float] = None,
        square: bool = False,
        max_memory: str = "8G",
    ) -> "Material":
        """One flash photo to a neural material, as `flashmat estimate` does.

        photo: a file (PNG, JPEG, EXR, HEIC/AVIF where built with libheif) or pixels
        [3, H, W] / [H, W, 3]: uint8 is sRGB; floats need encoding="srgb" or "linear".
        fov: field of view across the shorter side in degrees (files: from the EXIF by
        default; pixels: the model's own 28). size: the map's shorter side (multiple of 8).
        exposure_mode: calibrated, calibrated-grey, normalized, calibrated-clipping,
        calibrated-capped or off (`flashmat estimate --help`). exposure: stops added.
        Raises FileNotFoundError, ValueError, MemoryError.
        """

class Material:
    """A relightable neural material: per-pixel codes and the neural BRDF that renders them."""

    codes: torch.Tensor
    """The neural map [C, H, W], float32, on the material's device; the tensor itself (no copy)."""
    @property
    def input_photo(self) -> torch.Tensor:
        """The linear photo the material was estimated from, [3, H, W]."""
    @property
    def size(self) -> tuple[int, int]:
        """(H, W) of the neural map."""
    @property
    def device(self) -> str: ...
    @property
    def gain(self) -> tuple[float, float, float]:
        """Exposure and white balance (R, G, B) every render is multiplied by."""
    @property
    def info(self) -> dict:
        """model_id, source, fov_deg, ldr_input, refined."""
    def parameters(self) -> dict[str, torch.Tensor]:
        """The renderer's weights by name (the tensors themselves, frozen until requires_grad_())."""
    def render(self, light: Positions, view: Optional[Positions] = None, size: Optional[int] = None) -> torch.Tensor:
        """Linear HDR radiance [3, H, W] (or [K, 3, H, W] for [K, 3] positions) under a point light
        at `light`, seen from `view` (default overhead, as in the photo). Material units: the
        shorter side spans [-1, 1], z > 0. Differentiable."""
    def render_dirs(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Radiance [3, H, W] (or [K, 3, H, W]) for per-pixel unit directions wi, wo [H, W, 3]
        (or [K, H, W, 3]) towards the light and the camera. Differentiable in codes, weights and
        directions."""
    def save(self, path: Path) -> None:
        """Writes a .nmat file (atomically)."""
    def to(self, device: Device) -> "Material":
        """The same material on another device."""
    def clone(self) -> "Material":
        """An independent copy."""
    def fit(self, steps: Optional[int] = None, samples: Optional[int] = None, output: Optional[Path] = None) -> dict[str, torch.Tensor]:
        """PBR maps (GGX fitted per pixel, as `flashmat fit`): diffuse, specular, roughness, normal,
        base_color, metallic, error; with `output`, also the folder `flashmat fit -o` writes."""
    def view(self, path: Path, light: Optional[Sequence[float]] = None, view: Optional[Sequence[float]] = None) -> None:
        """Writes the material's browser page (`flashmat view`)."""
    def refine(self, photo: Optional[torch.Tensor] = None, steps: int = 100) -> str:
        """Refines the codes in place on `photo` ([3, H, W] linear; default the input photo).
        Returns the report line."""

def load_model(path: Optional[Path] = None, device: Device = "cpu") -> Model:
    """A model file, or the bundled model."""

def load(path: Path, device: Device = "cpu") -> Material:
    """Loads a .nmat material."""

def capture(
    folder: Path,
    *,
    photos: Optional[int] = None,
    size: int = 256,
    steps: Optional[int] = None,
    photo_gains: bool = False,
    model: Optional[Path] = None,
    device: Device = "cpu",
) -> Material:
    """One material from several photos of a capture folder (`flashmat estimate --capture`)."""
