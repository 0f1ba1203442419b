"""Generator settings: one dataclass, named presets, and the knobs an experiment can turn."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from difftex.errors import DifftexError


@dataclass(frozen=True)
class BuildingSpec:
    """One building: a style and its size in metres (the rest is drawn from the seed)."""

    name: str
    style: str  # box | gable | lshape | tower | courtyard
    width: float  # footprint extent along x
    depth: float  # footprint extent along y
    height: float  # eave / main roof height
    character: str = "office"  # office | shop | residential | civic; steers facade content


@dataclass(frozen=True)
class SynthConfig:
    """Every parameter of a generated scene; written verbatim into the manifest."""

    buildings: tuple[BuildingSpec, ...]
    views: int = 20  # training photos per building
    street_fraction: float = 0.3  # share of street-level photos among them
    held_out_views: int = 4  # occluder-free evaluation views per building
    width: int = 320
    height: int = 240
    spp: int = 16
    gt_spp: int = 16
    gt_long_side: int = 512  # longest side of a ground-truth map, texels
    texture_density: float = 80.0  # facade bitmap pixels per metre
    texture_max_side: int = 2048
    pose_noise_rot_deg: float = 0.0  # std of the written rotation error (degrees)
    pose_noise_trans: float = 0.0  # std of the written camera-centre error (metres)
    exposure_range: float = 0.5  # max |log2 gain| of a photo (stops)
    white_balance: float = 0.05  # std of per-channel log gain
    image_noise: float = 0.004  # std of additive Gaussian noise in linear units
    distortion: float = 0.0  # SIMPLE_RADIAL k; 0 writes PINHOLE cameras
    occluders: bool = True
    occluder_count: int = -1  # -1: scale with the building's perimeter
    relief_depth: float = 0.4  # window recess / cornice protrusion (metres); 0 = flat facades
    balconies: bool = True
    sun: bool = True  # directional sun besides the sky; False = sky only
    max_depth: int = 3  # path length: direct light plus one bounce, so recesses are shaded
    points3d: int = 300  # points of the COLMAP model sampled on the detailed facades
    previews: bool = True
    variant: str = "auto"  # auto | llvm_ad_rgb | scalar_rgb

    def replace(self, **changes) -> SynthConfig:
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(changes) - names)
        if bad:
            raise DifftexError(f"unknown synth setting(s): {', '.join(bad)} (known: {', '.join(sorted(names))})")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


PRESETS: dict[str, SynthConfig] = {
    # README example and CI scene: seconds to generate, yet every difficulty is present.
    "tiny": SynthConfig(
        buildings=(BuildingSpec("tiny", "gable", 12.0, 8.0, 7.0, "shop"),),
        views=20,
        held_out_views=3,
        width=320,
        height=240,
        spp=16,
        gt_spp=16,
        gt_long_side=512,
        texture_density=60.0,
        points3d=200,
    ),
    # The paper's virtual data set (Hall, Mall, Resident, Archive, Hyundai), 200 views each.
    "paper": SynthConfig(
        buildings=(
            BuildingSpec("hall", "box", 46.0, 28.0, 14.0, "civic"),
            BuildingSpec("mall", "lshape", 54.0, 40.0, 12.0, "shop"),
            BuildingSpec("resident", "courtyard", 40.0, 34.0, 18.0, "residential"),
            BuildingSpec("archive", "gable", 30.0, 18.0, 11.0, "civic"),
            BuildingSpec("hyundai", "tower", 36.0, 30.0, 12.0, "office"),
        ),
        views=200,
        street_fraction=0.25,
        held_out_views=20,
        width=1024,
        height=768,
        spp=16,
        gt_spp=32,
        gt_long_side=2048,
        texture_density=80.0,
        texture_max_side=4096,
        points3d=600,
    ),
}


def get_preset(name: str) -> SynthConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise DifftexError(f"unknown synth preset '{name}' (known: {', '.join(PRESETS)})") from None
