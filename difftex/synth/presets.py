"""Generator settings: one dataclass, named presets, and the knobs an experiment can turn."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from difftex.errors import DifftexError
from difftex.synth.camera_model import CameraModel


@dataclass(frozen=True)
class BuildingSpec:
    """One building: a style and its size in metres (the rest is drawn from the seed)."""

    name: str
    style: str  # box | gable | lshape | tower | courtyard
    width: float  # footprint extent along x
    depth: float  # footprint extent along y
    height: float  # eave / main roof height
    character: str = "office"  # office | shop | residential | civic; steers facade content


SAMPLERS = ("independent", "stratified", "multijitter", "orthogonal", "ldsampler")  # Mitsuba 3's


@dataclass(frozen=True)
class SynthConfig:
    """Every parameter of a generated scene; written verbatim into the manifest."""

    buildings: tuple[BuildingSpec, ...]
    views: int = 20  # training photos per building
    street_fraction: float = 0.3  # share of street-level photos among them
    # drone orbits: (distance factor of the footprint radius, height factor of the roof), cameras.make_views
    drone_rings: tuple[tuple[float, float], ...] = ((1.6, 0.55), (1.9, 1.0), (2.3, 1.6))
    held_out_views: int = 4  # occluder-free evaluation views per building
    width: int = 320
    height: int = 240
    spp: int = 16  # samples per pixel of the photos (rounded up as the sampler wants: render.effective_spp)
    gt_spp: int = 16  # samples per texel of the ground-truth maps
    heldout_spp: int = 0  # samples per pixel of the held-out views; 0 = gt_spp
    sampler: str = "independent"  # Mitsuba sampler of every render: independent | ldsampler | multijitter | ...
    gt_long_side: int = 512  # longest side of a ground-truth map, texels
    texture_density: float = 80.0  # facade bitmap pixels per metre
    texture_max_side: int = 2048
    pose_noise_rot_deg: float = 0.0  # std of the written rotation error (degrees)
    pose_noise_trans: float = 0.0  # std of the written camera-centre error (metres)
    exposure_range: float = 0.5  # max |log2 gain| of a photo (stops)
    white_balance: float = 0.05  # std of per-channel log gain
    image_noise: float = 0.004  # legacy: std of additive Gaussian noise, linear units; only with iso 0
    iso: float = 0.0  # camera model (camera_model.py): sensor ISO; 0 = no Poisson-Gaussian sensor noise
    full_well: float = 20000.0  # electrons a pixel holds at ISO 100
    read_noise: float = 3.0  # read-out noise std, electrons
    lens_blur: float = 0.0  # Gaussian PSF std of the photos, pixels
    jpeg_quality: int = 0  # 0: 8-bit PNG photos; 1-100: JPEG photos (.jpg) at this quality
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

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLERS:
            raise DifftexError(f"unknown Mitsuba sampler '{self.sampler}' (known: {', '.join(SAMPLERS)})")
        if min(self.spp, self.gt_spp) < 1 or self.heldout_spp < 0:
            raise DifftexError(f"spp and gt_spp must be >= 1 and heldout_spp >= 0, got {self.spp}, {self.gt_spp}, "
                               f"{self.heldout_spp}")
        # A manifest read back from JSON holds lists; a frozen config must stay hashable.
        object.__setattr__(self, "drone_rings", tuple(tuple(float(x) for x in r) for r in self.drone_rings))
        if not self.drone_rings or any(len(r) != 2 or r[0] <= 0 or r[1] < 0 for r in self.drone_rings):
            raise DifftexError(f"drone_rings must be (distance factor > 0, height factor >= 0) pairs, got "
                               f"{self.drone_rings}")
        self.camera_model()  # checks the camera's parameters

    def replace(self, **changes) -> SynthConfig:
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(changes) - names)
        if bad:
            raise DifftexError(f"unknown synth setting(s): {', '.join(bad)} (known: {', '.join(sorted(names))})")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def camera_model(self) -> CameraModel:
        """The photo pipeline these settings describe (checks its parameters)."""
        return CameraModel(iso=self.iso, full_well=self.full_well, read_noise=self.read_noise,
                           lens_blur=self.lens_blur, jpeg_quality=self.jpeg_quality,
                           image_noise=self.image_noise if self.iso == 0 else 0.0)

    @property
    def held_out_spp(self) -> int:
        return self.heldout_spp or self.gt_spp


SURVEY = dict(
    views=200,
    street_fraction=0.05,  # ~10 street-level photos among 200
    # Higher than the old presets' rings: the camera looks 20-45 degrees down, as an oblique survey's gimbal.
    drone_rings=((1.3, 1.5), (1.6, 2.4), (1.9, 3.4)),
    held_out_views=10,
    width=800,
    height=600,
    sampler="ldsampler",
    spp=256,  # render noise half the ISO-100 sensor's (RMS) at full size, below it at 2-4x (photo_noise.md)
    gt_spp=1024,
    heldout_spp=256,
    gt_long_side=512,
    texture_density=80.0,
    texture_max_side=4096,
    pose_noise_rot_deg=0.05,  # with pose_noise_trans: about 1 px reprojection error at 800x600
    pose_noise_trans=0.03,
    exposure_range=0.3785,  # log2(1.3): gain within +-30 %
    white_balance=0.03,
    image_noise=0.0,
    iso=100.0,
    full_well=20000.0,
    read_noise=3.0,
    lens_blur=0.5,
    jpeg_quality=90,
    relief_depth=0.28,
    balconies=True,
    occluders=True,
    points3d=600,
)
SURVEY_TINY = dict(views=12, held_out_views=2, width=200, height=150, street_fraction=0.2, spp=16, gt_spp=256,
                   heldout_spp=64, gt_long_side=128, texture_density=40.0, texture_max_side=1024, points3d=60,
                   previews=False)

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
    # Looks like a real survey (issue #30): a drone orbiting three buildings at several heights plus
    # a few street photos, JPEGs from a camera with realistic sensor noise, poses off by about a
    # pixel, exposure +-30 %, and renders converged far below that camera noise
    # (docs/synth.md, *The survey preset*, has the measurements behind each number).
    "survey": SynthConfig(
        buildings=(
            BuildingSpec("lblock", "lshape", 40.0, 30.0, 13.0, "shop"),
            BuildingSpec("gable", "gable", 26.0, 14.0, 10.0, "civic"),
            BuildingSpec("courtyard", "courtyard", 34.0, 30.0, 16.0, "residential"),
        ),
        **SURVEY,
    ),
    # One small survey building for tests: seconds to render, the same camera and sampler.
    "survey-tiny": SynthConfig(
        buildings=(BuildingSpec("tiny", "gable", 12.0, 8.0, 7.0, "residential"),),
        **{**SURVEY, **SURVEY_TINY},
    ),
}

# Districts for scale tests (difftex.synth.district.DistrictConfig keywords; docs/synth.md, *Districts*):
# about 9 polygons per building, photos 160x120, no ground truth.
DISTRICTS: dict[str, dict] = {
    "city-block": dict(buildings=12, views=10),  # about 100 polygons, 120 photos
    "city": dict(buildings=120, views=84),  # about 1,100 polygons, 10,080 photos
}


def get_preset(name: str) -> SynthConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise DifftexError(f"unknown synth preset '{name}' (known: {', '.join(PRESETS)})") from None
