"""Named scenarios: the range of lawns, landmark layouts, ground and sensors a mower meets.

Each preset combines a lawn (a random smooth one of a perimeter, or a shape: L, U, a long
strip), a landmark layout (how many, how far from the edge, how high; trees in flower beds
inside the lawn), the ground (flat, a slope, bumps) and the sensors (a gyro grade of
:data:`~mowerhw.sim.sensors.IMU_GRADES`, the ground-speed sensor's errors, the camera's
latency, losses and pixel noise). A seed draws one instance. ``paper`` is the paper's §V and
stays as it is; the others are the matrix the estimators are judged on (``mowerhw eval``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from mowerhw.sim.sensors import (
    IMU_GRADES,
    PAPER_SENSORS,
    CameraTiming,
    SensorSuite,
    SpeedModel,
)


@dataclass(frozen=True)
class Scenario:
    """What a simulated yard looks like; a seed draws one instance."""

    name: str
    perimeter_m: float  # of a random smooth lawn (ignored for a ``shape``)
    n_landmarks: int  # around the edge (trees in beds come on top)
    speed_mps: float
    landmark_distance_m: tuple[float, float]  # from the lawn edge (inside or outside)
    landmark_height_m: tuple[float, float]  # above the ground
    max_range_m: float  # the camera resolves a landmark up to this distance
    n_harmonics: int = 2
    amplitude: float = 0.15
    camera_height_m: float = 0.8
    standstill_s: float = 2.0
    shape: str = ""  # a polygonal lawn of mowerhw.sim.lawn.SHAPES instead
    beds: int = 0  # round flower beds inside (keep-out zones), each with a tree (a landmark)
    slope_deg: float = 0.0  # the ground rises this steeply in a random direction
    bumps_per_m2: float = 0.0  # bumps and dips of 3–8 cm, 0.3–0.6 m wide
    sensors: SensorSuite = field(default_factory=lambda: PAPER_SENSORS)
    #: share of the landmarks that come as look-alike pairs: the same panel, turned half
    #: round the centre of a (symmetric) lawn — a symmetric garden (issue 18)
    twins: float = 0.0
    description: str = ""


def _sensors(
    imu: str = "vn100",
    speed: SpeedModel | None = None,
    camera: CameraTiming | None = None,
) -> SensorSuite:
    return SensorSuite(IMU_GRADES[imu], speed or SpeedModel(), camera or CameraTiming())


_JITTERY = CameraTiming((0.05, 0.15), stamp_jitter_s=0.003, frame_drop=0.1, pixel_sigma=3.0)

SCENARIOS: dict[str, Scenario] = {
    # The paper's §V: 15 landmarks at random in 3D, a closed teach loop of about 60 s.
    "paper": Scenario(
        name="paper",
        perimeter_m=26.0,
        n_landmarks=15,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 6.0),
        landmark_height_m=(0.3, 2.5),
        max_range_m=30.0,
        description="the paper's §V: 15 random landmarks, VN-100, 3 px",
    ),
    # A larger, gently concave lawn for scaling: ≥ 150 m perimeter, ≥ 60 landmarks, a
    # limited camera range so landmarks come and go (keyframes change).
    "large": Scenario(
        name="large",
        perimeter_m=160.0,
        n_landmarks=80,
        speed_mps=0.6,
        landmark_distance_m=(1.5, 8.0),
        landmark_height_m=(0.3, 3.0),
        max_range_m=15.0,
        n_harmonics=3,
        amplitude=0.25,
        description="160 m perimeter, 80 landmarks seen up to 15 m",
    ),
    "far": Scenario(
        name="far",
        perimeter_m=40.0,
        n_landmarks=20,
        speed_mps=0.5,
        landmark_distance_m=(6.0, 20.0),
        landmark_height_m=(0.5, 4.0),
        max_range_m=30.0,
        description="a convex lawn, landmarks 6–20 m away only (little parallax)",
    ),
    "L-slope": Scenario(
        name="L-slope",
        perimeter_m=0.0,
        shape="L",
        n_landmarks=25,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 10.0),
        landmark_height_m=(0.3, 3.0),
        max_range_m=25.0,
        slope_deg=7.0,
        sensors=_sensors(
            "bmi088",
            SpeedModel(white=0.005, scale_error=(0.02, 0.05), day_sigma=0.005),
            _JITTERY,
        ),
        description="an L-shaped lawn on a 7° hillside, BMI088, 2–5 % speed scale error, "
        "50–150 ms camera latency, 10 % frames recognising nothing",
    ),
    "U-sparse": Scenario(
        name="U-sparse",
        perimeter_m=0.0,
        shape="U",
        n_landmarks=11,
        speed_mps=0.45,
        landmark_distance_m=(2.0, 12.0),
        landmark_height_m=(0.3, 3.0),
        max_range_m=25.0,
        sensors=_sensors(
            "mpu6050",
            SpeedModel(white=0.008, scale_error=(0.02, 0.03), day_sigma=0.005),
            CameraTiming((0.05, 0.15), 0.003, frame_drop=0.2, bearing_drop=0.1, pixel_sigma=5.0),
        ),
        description="a U-shaped lawn, 11 landmarks (≈ 8 in view), MPU-6050, 5 px, 2–3 % speed "
        "scale error, 20 % frames recognising nothing and 10 % bearings missed",
    ),
    "strip-bumps": Scenario(
        name="strip-bumps",
        perimeter_m=0.0,
        shape="strip",
        n_landmarks=30,
        speed_mps=0.5,
        landmark_distance_m=(1.0, 15.0),
        landmark_height_m=(0.2, 4.0),
        max_range_m=25.0,
        bumps_per_m2=0.15,
        sensors=_sensors(
            "bmi088",
            SpeedModel(
                white=0.006,
                scale_error=(0.02, 0.03),
                day_sigma=0.005,
                slip_per_min=2.0,
                slip_fraction=0.15,
            ),
            _JITTERY,
        ),
        description="a 32 x 4 m strip on bumpy ground, near and far landmarks, BMI088, "
        "wheel slip twice a minute",
    ),
    "trees-dense": Scenario(
        name="trees-dense",
        perimeter_m=45.0,
        n_landmarks=60,
        speed_mps=0.45,
        landmark_distance_m=(1.0, 8.0),
        landmark_height_m=(0.2, 3.0),
        max_range_m=20.0,
        beds=3,
        amplitude=0.2,
        sensors=_sensors("vn100", camera=_JITTERY),
        description="60 landmarks and 3 flower beds with trees inside the lawn (keep-out "
        "zones when mowing), VN-100",
    ),
    "concave-mems": Scenario(
        name="concave-mems",
        perimeter_m=38.0,
        n_landmarks=30,
        speed_mps=0.45,
        landmark_distance_m=(1.0, 12.0),
        landmark_height_m=(0.2, 3.5),
        max_range_m=25.0,
        n_harmonics=3,
        amplitude=0.3,
        bumps_per_m2=0.1,
        sensors=_sensors(
            "mpu6050",
            SpeedModel(white=0.006, scale_error=(0.02, 0.03), day_sigma=0.005),
            CameraTiming((0.05, 0.15), 0.003, bearing_drop=0.1, pixel_sigma=3.0),
        ),
        description="a concave lawn, 30 landmarks up to 12 m, bumps, MPU-6050, 10 % bearings lost",
    ),
    "slope-slip": Scenario(
        name="slope-slip",
        perimeter_m=32.0,
        n_landmarks=20,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 10.0),
        landmark_height_m=(0.3, 3.0),
        max_range_m=25.0,
        slope_deg=10.0,
        sensors=_sensors(
            "mpu6050",
            SpeedModel(
                white=0.005,
                scale_error=(0.03, 0.05),
                day_sigma=0.01,
                slip_per_min=3.0,
                slip_fraction=0.2,
            ),
            CameraTiming((0.05, 0.15), 0.003, frame_drop=0.3, pixel_sigma=3.0),
        ),
        description="a 10° hillside, MPU-6050, 3–5 % speed scale error, slip three times a "
        "minute, 30 % frames recognising nothing",
    ),
    # Two lawns joined by a path, taught in one drive (mowerhw.sim.garden; issue 17's bench).
    "garden": Scenario(
        name="garden",
        perimeter_m=0.0,
        shape="garden",
        n_landmarks=36,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 6.0),
        landmark_height_m=(0.3, 2.5),
        max_range_m=30.0,
        description="two 8 × 6 m lawns joined by a 2 m path, 36 landmarks, VN-100",
    ),
    # A symmetric garden where looks deceive (issue 18): a rectangular lawn, two thirds of the
    # landmarks in identical pairs half round its centre. From (x, y, ψ) and from the same
    # pose turned half round the centre, those twins look the same; only the other third
    # tells the two apart. A wrong but confident match is likely here.
    "look-alike": Scenario(
        name="look-alike",
        perimeter_m=0.0,
        shape="rectangle",
        n_landmarks=24,
        speed_mps=0.45,
        landmark_distance_m=(1.5, 6.0),
        landmark_height_m=(0.3, 2.5),
        max_range_m=30.0,
        twins=2.0 / 3.0,
        description="a 12 × 8 m rectangle, 24 landmarks, 16 of them in identical pairs half "
        "round its centre (a symmetric garden)",
    ),
}

#: the presets of the matrix (all but the scaling one, the two-lawn garden of the bench and
#: the look-alike garden of the relocalizer)
MATRIX = [name for name in SCENARIOS if name not in ("large", "garden", "look-alike")]


def with_sensors(scenario: Scenario, sensors: SensorSuite) -> Scenario:
    return replace(scenario, sensors=sensors)
