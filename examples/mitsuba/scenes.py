"""Scene descriptions (Mitsuba 3 Python dicts) of the flashmat examples.

Conventions shared with flashmat (docs/NMAT.md): BSDF `eval` returns R / pi,
R the radiance flashmat renders for a unit point light without falloff.
Mitsuba's point light does fall off (I / r^2), so each light gets the
intensity pi * r0^2 with r0 its distance to the object's centre (plane) or
nearest point (sphere): there, pixel value = R, directly comparable with
flashmat's renders and photos.
"""
import math

# The input photo's camera and light: straight overhead at d = 1 / tan(14 deg)
# (REFERENCE section 1: the 28 degree model camera).
INPUT_DISTANCE = 1.0 / math.tan(math.radians(14.0))
INPUT_LIGHT = (0.0, 0.0, INPUT_DISTANCE)
# A grazing light from the upper left, for the plane's second view.
SIDE_LIGHT = (-2.5, 1.5, 1.5)

# Sphere figure: camera on +z looking at a unit sphere; point light up and to the left of it.
SPHERE_CAMERA = (0.0, 0.0, 4.0)
SPHERE_FOV = 34.0
SPHERE_LIGHT = (-1.5, 1.5, 4.0)


def _norm(v):
    return math.sqrt(sum(x * x for x in v))


def _film_sensor(mi, origin, fov, res, spp):
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=list(origin), target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": spp},
    }


def _integrator():
    # One point light: emitter sampling only (a BSDF-sampled direction never hits a point light).
    return {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}


def point_light(position, r0):
    return {"type": "point", "position": list(position), "intensity": {"type": "rgb", "value": math.pi * r0 * r0}}


def sphere_scene(mi, bsdf, res, spp):
    """A unit sphere at the origin with its poles on the y axis, so that its
    shading frame (s = dp/du along the parallels, n outwards) has x to the
    right and y up where it faces the camera, like the photo's material frame."""
    return {
        "type": "scene",
        "integrator": _integrator(),
        "sensor": _film_sensor(mi, SPHERE_CAMERA, SPHERE_FOV, res, spp),
        "light": point_light(SPHERE_LIGHT, _norm(SPHERE_LIGHT) - 1.0),
        "sphere": {"type": "sphere", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90), "bsdf": bsdf},
    }


def plane_scene(mi, bsdf, light, res, spp):
    """The material square [-1, 1]^2 at z = 0 (Mitsuba's rectangle: uv = ((x+1)/2, (y+1)/2)),
    seen by the input photo's camera (28 degrees, overhead at d) and lit by a point light."""
    return {
        "type": "scene",
        "integrator": _integrator(),
        "sensor": _film_sensor(mi, (0.0, 0.0, INPUT_DISTANCE), 28.0, res, spp),
        "light": point_light(light, _norm(light)),
        "rect": {"type": "rectangle", "bsdf": bsdf},
    }
