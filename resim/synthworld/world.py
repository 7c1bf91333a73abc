"""The synthetic road network and its scenery.

One *world* per episode: a route (the road the ego follows, built from a
curvature profile of straights, gentle curves and 90-degree intersection turns,
both ways), the crossing roads of its intersections, roadside trees / bushes /
posts, parked cars on the shoulder, a lead car in the ego lane and oncoming
cars in the other lane, and an appearance (grass/asphalt colours, sky, light,
fog). Everything is drawn from one ``numpy.random.Generator``, so a seed fixes
the world.

Frame: right-handed, x/y metres in the ground plane, heading CCW from +x. The
road has two 3.5 m lanes; traffic drives on the right, so the ego lane centre is
``LANE_OFFSET_M = -1.75`` m (to the right) of the route centreline.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

ROAD_HALF_WIDTH_M = 3.5
LANE_OFFSET_M = -1.75
DS_M = 0.5                  # route sampling step
TURN_RADIUS_M = 11.0        # centreline radius of an intersection turn
INTERSECTION_CLEAR_M = 8.0  # no lane markings / scenery this close to an intersection centre


@dataclass
class Road:
    """A polyline road: points (N, 2) every DS_M metres with headings (N,) and arc length (N,)."""

    xy: np.ndarray
    heading: np.ndarray
    s: np.ndarray
    curvature: np.ndarray

    def offset(self, lateral_m: float) -> np.ndarray:
        """Points shifted ``lateral_m`` to the left (negative = right) of the centreline."""
        n = np.c_[-np.sin(self.heading), np.cos(self.heading)]
        return self.xy + lateral_m * n

    def at(self, s: np.ndarray | float, lateral_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated (xy (..., 2), heading (...)) at arc length s, shifted laterally."""
        s = np.clip(np.asarray(s, float), self.s[0], self.s[-1])
        h = np.interp(s, self.s, self.heading)
        x = np.interp(s, self.s, self.xy[:, 0]) - lateral_m * np.sin(h)
        y = np.interp(s, self.s, self.xy[:, 1]) + lateral_m * np.cos(h)
        return np.stack([x, y], -1), h


def road_from_curvature(start_xy, start_heading: float, curvature: np.ndarray) -> Road:
    """Integrate a per-step curvature profile (1/m, one value per DS_M step) exactly (arcs)."""
    k = np.asarray(curvature, float)
    h = start_heading + np.r_[0.0, np.cumsum(k * DS_M)]
    hm = 0.5 * (h[:-1] + h[1:])
    # chord of an arc of length ds and curvature k: length ds*sinc(k ds/2), direction = mid heading
    chord = DS_M * np.sinc(k * DS_M / 2 / np.pi)
    xy = np.zeros((len(h), 2))
    xy[0] = start_xy
    xy[1:] = start_xy + np.cumsum(np.c_[chord * np.cos(hm), chord * np.sin(hm)], axis=0)
    return Road(xy=xy, heading=h, s=np.arange(len(h)) * DS_M, curvature=np.r_[k, k[-1:]])


def straight_road(a, b) -> Road:
    a, b = np.asarray(a, float), np.asarray(b, float)
    L = float(np.hypot(*(b - a)))
    n = max(2, int(L / DS_M) + 1)
    t = np.linspace(0, 1, n)[:, None]
    hd = math.atan2(b[1] - a[1], b[0] - a[0])
    return Road(xy=a + t * (b - a), heading=np.full(n, hd), s=t[:, 0] * L, curvature=np.zeros(n))


@dataclass
class Segment:
    kind: str          # straight | curve | turn | cross
    length_m: float
    curvature: float   # 1/m, + = left
    s_start: float = 0.0


@dataclass
class Appearance:
    grass_rgb: tuple[float, float, float]
    grass2_rgb: tuple[float, float, float]
    asphalt_gray: float
    centre_line_rgb: tuple[float, float, float]
    sky_zenith_rgb: tuple[float, float, float]
    sky_horizon_rgb: tuple[float, float, float]
    hills_rgb: tuple[float, float, float]
    brightness: float
    fog_visibility_m: float
    name: str


SKIES = {  # name: zenith, horizon, brightness range, fog visibility range
    "clear": ((70, 120, 200), (175, 205, 235), (0.95, 1.1), (250, 600)),
    "overcast": ((150, 155, 165), (195, 198, 202), (0.8, 0.95), (120, 300)),
    "dusk": ((60, 60, 110), (235, 160, 110), (0.65, 0.8), (150, 400)),
    "fog": ((185, 185, 185), (205, 205, 205), (0.8, 0.9), (45, 90)),
    "night": ((10, 12, 30), (45, 50, 80), (0.45, 0.55), (80, 160)),
}
SKY_WEIGHTS = {"clear": 0.4, "overcast": 0.25, "dusk": 0.15, "fog": 0.1, "night": 0.1}


def sample_appearance(rng: np.random.Generator) -> Appearance:
    names = list(SKY_WEIGHTS)
    name = names[rng.choice(len(names), p=np.array(list(SKY_WEIGHTS.values())))]
    zen, hor, br, fog = SKIES[name]
    grass = [(70, 115, 45), (110, 125, 55), (120, 105, 70), (60, 95, 50)][rng.integers(4)]
    jitter = lambda c, a=12: tuple(float(np.clip(v + rng.uniform(-a, a), 0, 255)) for v in c)  # noqa: E731
    return Appearance(
        grass_rgb=jitter(grass), grass2_rgb=jitter(tuple(v * 0.75 for v in grass)),
        asphalt_gray=float(rng.uniform(70, 105)),
        centre_line_rgb=(230, 190, 40) if rng.random() < 0.5 else (235, 235, 235),
        sky_zenith_rgb=jitter(zen, 8), sky_horizon_rgb=jitter(hor, 8),
        hills_rgb=jitter((95, 110, 120), 15), brightness=float(rng.uniform(*br)),
        fog_visibility_m=float(rng.uniform(*fog)), name=name,
    )


@dataclass
class Props:
    """Static scenery as arrays: billboards (trees, bushes, posts) and parked cars."""

    xy: np.ndarray          # (M, 2)
    kind: np.ndarray        # (M,) int: 0 tree, 1 bush, 2 post
    height_m: np.ndarray    # (M,)
    width_m: np.ndarray     # (M,) canopy / post width
    rgb: np.ndarray         # (M, 3) float
    radius_m: np.ndarray    # (M,) collision radius


PROP_TREE, PROP_BUSH, PROP_POST = 0, 1, 2


@dataclass
class Car:
    """A box car. Static (parked) when speed_mps == 0, else driven along ``road`` at ``lateral_m``."""

    road_index: int         # -1: static at (x, y, yaw)
    s0_m: float
    speed_mps: float        # signed: negative drives against the road direction
    lateral_m: float
    rgb: tuple[float, float, float]
    xy_yaw: tuple[float, float, float] = (0.0, 0.0, 0.0)
    length_m: float = 4.5
    width_m: float = 1.9
    height_m: float = 1.5


@dataclass
class World:
    route: Road
    segments: list[Segment]
    crossings: list[Road]
    intersections: np.ndarray      # (K, 2) centres
    props: Props
    cars: list[Car]
    appearance: Appearance
    start_s_m: float
    nominal_speed_mps: float
    roads: list[Road] = field(default_factory=list)   # route + crossings (for off-road tests)
    # |curvature| per route sample the driver plans its speed on (None: the route's own); a counterfactual
    # fork (fork.py) sets the sharpest of its branches, so every branch slows for the junction alike
    speed_curvature: np.ndarray | None = None
    fork: dict | None = None      # a fork's branch, where it splits (route_s_m) and the junction's centre
    pace: dict | None = None      # a pace fork's branch, speed factor and split time (pace.py)

    def lane_path(self) -> np.ndarray:
        return self.route.offset(LANE_OFFSET_M)

    def car_poses(self, t_s: float) -> np.ndarray:
        """(num_cars, 3) x, y, yaw of every car at time t_s."""
        out = np.zeros((len(self.cars), 3))
        for i, c in enumerate(self.cars):
            if c.road_index < 0:
                out[i] = c.xy_yaw
                continue
            road = self.roads[c.road_index]
            s = c.s0_m + c.speed_mps * t_s
            xy, h = road.at(s, c.lateral_m)
            out[i] = (*xy, h + (math.pi if c.speed_mps < 0 else 0.0))
        return out

    def distance_to_roads(self, xy: np.ndarray) -> np.ndarray:
        """Distance (m) from points (..., 2) to the nearest road centreline sample (any road)."""
        pts = np.concatenate([r.xy[::2] for r in self.roads])
        d2 = ((xy[..., None, :] - pts) ** 2).sum(-1)
        return np.sqrt(d2.min(-1))


def _segments(rng: np.random.Generator, total_m: float, first_turn_sign: int) -> list[Segment]:
    segs = [Segment("straight", float(rng.uniform(25, 40)), 0.0)]
    sign = first_turn_sign
    while sum(s.length_m for s in segs) < total_m:
        r = rng.random()
        if r < 0.3:
            segs.append(Segment("straight", float(rng.uniform(15, 35)), 0.0))
        elif r < 0.6:
            ang = math.radians(rng.uniform(30, 75))
            rad = float(rng.uniform(25, 55))
            segs.append(Segment("curve", rad * ang, sign / rad))
            sign = sign if rng.random() < 0.3 else -sign
        elif r < 0.9:
            segs.append(Segment("turn", TURN_RADIUS_M * math.pi / 2, sign / TURN_RADIUS_M))
            segs.append(Segment("straight", float(rng.uniform(15, 25)), 0.0))
            sign = sign if rng.random() < 0.3 else -sign
        else:
            segs.append(Segment("cross", 40.0, 0.0))
    s = 0.0
    for seg in segs:
        seg.s_start = s
        s += seg.length_m
    return segs


def build_road(rng: np.random.Generator, duration_s: float, nominal_speed_mps: float,
                first_turn_sign: int = 1) -> World:
    """Draw one world long enough for ``duration_s`` of driving at up to twice ``nominal_speed_mps``."""
    total = 2.0 * nominal_speed_mps * duration_s + 80.0
    segs = _segments(rng, total, first_turn_sign)
    k = np.concatenate([np.full(max(1, int(round(sg.length_m / DS_M))), sg.curvature) for sg in segs])
    route = road_from_curvature(np.zeros(2), float(rng.uniform(-math.pi, math.pi)), k)
    # re-anchor segment starts on the sampled grid
    s = 0.0
    for sg in segs:
        sg.s_start = s
        s += max(1, int(round(sg.length_m / DS_M))) * DS_M
    crossings, centres = [], []
    for sg in segs:
        i0 = int(round(sg.s_start / DS_M))
        p0, h0 = route.xy[i0], route.heading[i0]
        d0 = np.array([math.cos(h0), math.sin(h0)])
        if sg.kind == "turn":
            sign = 1.0 if sg.curvature > 0 else -1.0
            c = p0 + TURN_RADIUS_M * d0
            side = np.array([math.cos(h0 + sign * math.pi / 2), math.sin(h0 + sign * math.pi / 2)])
            crossings.append(straight_road(p0, c + 30 * d0))           # the road goes on straight ahead
            crossings.append(straight_road(c, c - 30 * side))           # and the branch we do not take
            centres.append(c)
        elif sg.kind == "cross":
            c = p0 + 20 * d0
            side = np.array([-d0[1], d0[0]])
            crossings.append(straight_road(c - 35 * side, c + 35 * side))
            centres.append(c)
    centres_arr = np.array(centres).reshape(-1, 2)
    world = World(route=route, segments=segs, crossings=crossings, intersections=centres_arr,
                  props=None, cars=[], appearance=sample_appearance(rng), start_s_m=10.0,  # type: ignore[arg-type]
                  nominal_speed_mps=nominal_speed_mps)
    world.roads = [route] + crossings
    world.props = _scatter_props(rng, world)
    world.cars = _place_cars(rng, world)
    return world


def _scatter_props(rng: np.random.Generator, world: World) -> Props:
    cand = []
    for road in world.roads:
        s = float(rng.uniform(0, 6))
        while s < road.s[-1]:
            for side in (-1, 1):
                if rng.random() < 0.75:
                    (xy,), _ = road.at(np.array([s]), side * float(rng.uniform(5.5, 11.0)))
                    cand.append(xy)
            s += float(rng.uniform(5, 12))
    xy = np.array(cand).reshape(-1, 2)
    keep = world.distance_to_roads(xy) > 5.0
    if len(world.intersections):
        dc = np.sqrt(((xy[:, None] - world.intersections[None]) ** 2).sum(-1)).min(1)
        keep &= dc > INTERSECTION_CLEAR_M + 4
    xy = xy[keep]
    m = len(xy)
    kind = rng.choice(3, size=m, p=[0.55, 0.25, 0.20])
    height = np.where(kind == PROP_TREE, rng.uniform(4, 9, m), np.where(kind == PROP_BUSH, rng.uniform(0.8, 1.6, m),
                                                                       rng.uniform(1.0, 1.4, m)))
    width = np.where(kind == PROP_TREE, rng.uniform(2.5, 5, m), np.where(kind == PROP_BUSH, rng.uniform(1.2, 2.5, m), 0.15))
    base = np.array([[40, 90, 40], [50, 110, 45], [230, 230, 230]], float)
    rgb = np.clip(base[kind] + rng.uniform(-20, 20, (m, 3)), 0, 255)
    radius = np.where(kind == PROP_TREE, 0.4, np.where(kind == PROP_BUSH, 0.6, 0.15))
    return Props(xy=xy, kind=kind, height_m=height, width_m=width, rgb=rgb, radius_m=radius)


CAR_COLOURS = [(200, 30, 30), (30, 60, 170), (220, 220, 220), (40, 40, 40), (150, 150, 155), (30, 120, 60),
               (230, 180, 40)]


def _place_cars(rng: np.random.Generator, world: World) -> list[Car]:
    cars: list[Car] = []
    route = world.route
    colour = lambda: tuple(float(c) for c in CAR_COLOURS[rng.integers(len(CAR_COLOURS))])  # noqa: E731
    # a lead car in the ego lane, a little faster than the ego's nominal speed
    if rng.random() < 0.6:
        cars.append(Car(0, world.start_s_m + float(rng.uniform(25, 40)), world.nominal_speed_mps * 1.15,
                        LANE_OFFSET_M, colour()))
    # oncoming traffic in the other lane
    for _ in range(int(rng.integers(1, 4))):
        cars.append(Car(0, float(rng.uniform(60, route.s[-1])), -float(rng.uniform(6, 10)), -LANE_OFFSET_M, colour()))
    # parked cars on the shoulder (right side, sometimes left), away from intersections
    for _ in range(int(rng.integers(2, 6))):
        s = float(rng.uniform(world.start_s_m + 20, route.s[-1] - 10))
        side = -1 if rng.random() < 0.75 else 1
        (xy,), h = route.at(np.array([s]), side * (ROAD_HALF_WIDTH_M + 1.15))
        if len(world.intersections) and np.sqrt(((world.intersections - xy) ** 2).sum(1)).min() < 15:
            continue
        if world.distance_to_roads(xy[None])[0] < ROAD_HALF_WIDTH_M + 1.0:   # would stand on another road
            continue
        cars.append(Car(-1, 0.0, 0.0, 0.0, colour(), xy_yaw=(float(xy[0]), float(xy[1]), float(h[0]))))
    return cars
