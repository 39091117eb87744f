"""The wide cameras of the configs, and their twins in the independent renderer (not a test)."""
from __future__ import annotations

from independent_render import Fisheye, Unified

from sphere_servo.core.camera_models import FisheyeCamera, UnifiedCamera
from sphere_servo.pipeline.config import scenario

#: the cameras of config/params/fisheye.yaml and catadioptric.yaml, read from the configs
_FISH = scenario('fisheye').node_params('arm_sim')['camera']
_CATA = scenario('catadioptric').node_params('arm_sim')['camera']
FISHEYE = FisheyeCamera(px=_FISH['px'], py=_FISH['py'], u0=_FISH['u0'], v0=_FISH['v0'],
                        width=_FISH['width'], height=_FISH['height'], dist=tuple(_FISH['d']))
CATADIOPTRIC = UnifiedCamera(px=_CATA['px'], py=_CATA['py'], u0=_CATA['u0'], v0=_CATA['v0'],
                             width=_CATA['width'], height=_CATA['height'], xi=_CATA['xi'],
                             dist=tuple(_CATA['d']))
WIDE = {'fisheye': FISHEYE, 'catadioptric': CATADIOPTRIC}


def twin(cam):
    """Return the independent renderer's camera with the same parameters."""
    if isinstance(cam, FisheyeCamera):
        return Fisheye(cam.px, cam.py, cam.u0, cam.v0, cam.width, cam.height, tuple(cam.dist))
    return Unified(cam.px, cam.py, cam.u0, cam.v0, cam.width, cam.height, cam.xi,
                   tuple(cam.dist))
