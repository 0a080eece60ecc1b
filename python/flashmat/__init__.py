"""flashmat: one flash photograph of a flat material in, a relightable
neural material out, in PyTorch (docs/PYTHON.md).

    import flashmat
    model = flashmat.load_model()                    # the bundled model
    material = model.estimate("photo.jpg")           # a flashmat.Material
    image = material.render(light=(1.0, 0.5, 3.0))   # torch [3, H, W], linear HDR
    material.save("photo.nmat")

`material.codes` is the neural map itself (a torch tensor, no copy), and
`render` / `render_dirs` are differentiable. `flashmat.mitsuba` is the
Mitsuba 3 BSDF (`import flashmat.mitsuba`; it needs the `mitsuba` package).
"""
import importlib.util

__version__ = "0.1.0"

if importlib.util.find_spec("flashmat._flashmat") is None:
    # A source tree without the built extension (PYTHONPATH=python): the
    # pure-Python flashmat.mitsuba works; the rest needs `pip install`.
    def __getattr__(name):
        if name.startswith("__"):
            raise AttributeError(name)
        raise ImportError(
            f"flashmat.{name} needs flashmat's extension, which is not built here: "
            "pip install --no-build-isolation <flashmat checkout> (docs/PYTHON.md)"
        )

else:
    import torch

    try:
        from . import _flashmat
    except ImportError as error:  # a libtorch other than the one it was built against
        raise ImportError(
            f"flashmat's extension did not load with this environment's torch {torch.__version__} ({error}); "
            "it links the libtorch of the torch it was built with: reinstall flashmat here (pip install <flashmat checkout>)"
        ) from error

    def _release(version):
        return version.split("+")[0]

    if _release(_flashmat.TORCH_VERSION) != _release(torch.__version__):
        raise ImportError(
            f"flashmat was built against torch {_flashmat.TORCH_VERSION}, this environment has torch {torch.__version__}: "
            "reinstall flashmat here (pip install <flashmat checkout>) or install that torch"
        )

    from ._flashmat import Material, Model, capture, load, load_model  # noqa: F401

    #: The torch version flashmat's extension was built against.
    TORCH_VERSION = _flashmat.TORCH_VERSION
    #: The position of the photo's camera and flash (co-located, overhead): the
    #: default view of `render`; `render(OVERHEAD)` gives the photo back.
    OVERHEAD = _flashmat.OVERHEAD
    #: The `.nmat` format version flashmat writes.
    NMAT_VERSION = _flashmat.NMAT_VERSION

__all__ = ["Material", "Model", "capture", "load", "load_model", "TORCH_VERSION", "NMAT_VERSION", "OVERHEAD"]
