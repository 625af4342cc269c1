"""Scenes for the synthetic camera: faces, materials and ray casting.

A scene is a list of rectangular faces (an unbounded plane for the wall or
board), planar or bent into a cylindrical panel. Each face carries a material
whose reflectance at normal incidence ``R0(s, t)`` and scattering coefficient
``n(s, t)`` are maps in the face's own coordinates (metres along its axes
``u``, ``v``; on a cylindrical face ``s`` is the arc length, so a texture is not
stretched), so that a texture moves and turns with the specimen it belongs to.
A specimen is a box raised from the board towards the camera: a top face, flat
or cylindrical, and four side faces.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from surffin.simulate.camera import PinholeCamera, world_rays

__all__ = [
    "Face",
    "Geometry",
    "Material",
    "Scene",
    "Texture",
    "box_faces",
    "keyed_rng",
    "plane_face",
    "random_field",
    "render",
]

#: Grid samples per Gaussian smoothing length of a texture field.
_SAMPLES_PER_LENGTH = 2.0
_EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Texture:
    """One layer of a spatially correlated surface texture.

    Attributes
    ----------
    amplitude : float
        Standard deviation of the layer (relative for R0, absolute for n).
    length : float, metres
        Standard deviation of the Gaussian that smooths white noise into the field.
    period : float, metres
        The field repeats with this period along both surface axes; larger than
        the surface it covers unless repetition does not matter.
    """

    amplitude: float
    length: float
    period: float


@dataclass(frozen=True)
class Material:
    """A surface material: class means and textures of R0 and n.

    ``R0(s, t) = R0 * (1 + sum_k a_k T_k(s, t))`` and
    ``n(s, t) = n + sum_k b_k U_k(s, t)`` with unit-variance random fields
    ``T_k``, ``U_k`` (see :func:`random_field`), drawn once per material name
    and seed.

    Attributes
    ----------
    name : str
        Identifies the material's random fields (same name, same texture).
    R0 : float
        Mean reflectance at normal incidence.
    n : float
        Mean scattering coefficient (1 = Lambertian).
    R0_texture, n_texture : tuple of Texture
        Texture layers of R0 (relative) and n (absolute).
    """

    name: str
    R0: float
    n: float
    R0_texture: tuple[Texture, ...] = ()
    n_texture: tuple[Texture, ...] = ()


@dataclass(frozen=True, eq=False)
class Face:
    """A rectangle of a scene, planar or bent about an axis along ``v`` (a cylindrical panel).

    A cylindrical face of signed radius ``r`` holds the points
    ``centre + r sin(s/r) u + r (cos(s/r) - 1) normal + t v``: it touches the
    plane of ``centre``, ``u``, ``v`` along the line ``s = 0``, ``s`` is the arc
    length, and its outward normal at ``s`` is ``cos(s/r) normal + sin(s/r) u``.
    Its axis, ``centre - r normal``, lies behind the face when ``r > 0``
    (convex: it bulges towards the viewer) and in front of it when ``r < 0``
    (concave).

    Attributes
    ----------
    name : str
        E.g. ``"S1.top"``.
    centre : (3,) ndarray, metres
        World point at surface coordinates (0, 0).
    u, v : (3,) ndarray
        Orthonormal in-plane axes; surface coordinates ``s``, ``t`` are metres
        along them.
    normal : (3,) ndarray
        Outward unit normal (at ``s = 0`` on a cylindrical face); the face is
        seen only from this side.
    half_size : (float, float), metres
        Half extents along ``u`` (arc length on a cylindrical face) and ``v``;
        ``inf`` for an unbounded plane.
    material : Material
        What the face is made of.
    label : int
        Class index for a specimen's top face, -1 for any other face.
    radius : float or None, metres
        Signed radius of a cylindrical face: positive convex, negative concave;
        None for a planar face. A cylindrical face is bounded and spans at most
        a half turn (``half_size[0] <= pi/2 |radius|``).
    """

    name: str
    centre: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    half_size: tuple[float, float]
    material: Material
    label: int = -1
    radius: float | None = None

    def __post_init__(self):
        """Refuse a radius that is zero or not finite, or bends the face beyond a half turn."""
        if self.radius is not None and not (
            np.isfinite(self.radius) and self.radius != 0 and self.half_size[0] <= np.pi / 2 * abs(self.radius)
        ):
            raise ValueError(
                f"face {self.name}: radius must be finite and nonzero, and the face at most a half turn "
                f"(half size {self.half_size[0]} m along u <= pi/2 |radius|), got radius {self.radius!r}"
            )

    @property
    def curvature(self) -> float:
        """Signed curvature ``1 / radius``, 1/m; 0 for a planar face."""
        return 0.0 if self.radius is None else 1.0 / self.radius


def keyed_rng(seed: int, *key: str | int) -> np.random.Generator:
    """Make an independent random stream named by a key, reproducible for one seed.

    Streams of different keys are independent (``SeedSequence`` spawn keys), so
    what a view, texture or instrument draws does not depend on what else is
    drawn or in which order.

    Parameters
    ----------
    seed : int
        Root seed of the campaign (>= 0).
    *key : str or int
        Names the stream, e.g. ``("view", "S1", "v00")``.

    Returns
    -------
    Generator
    """
    spawn_key = tuple(zlib.crc32(str(part).encode("utf-8")) for part in key)
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=spawn_key))


def random_field(rng: np.random.Generator, size: int, length: float) -> np.ndarray:
    """Draw a periodic, spatially correlated random field of zero mean and unit variance.

    Parameters
    ----------
    rng : Generator
        Source of the white noise.
    size : int
        Grid samples along each axis.
    length : float, grid samples
        Standard deviation of the (periodic) Gaussian smoothing.

    Returns
    -------
    (size, size) ndarray of float64
        Exactly zero mean and unit standard deviation over the grid.
    """
    frequency = np.fft.fftfreq(size)
    half = np.fft.rfftfreq(size)
    transfer = np.exp(-2.0 * (np.pi * length) ** 2 * (frequency[:, None] ** 2 + half[None, :] ** 2))
    field = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((size, size))) * transfer, s=(size, size))
    field -= field.mean()
    return field / field.std()


class _Layer:
    """One texture layer realised on its periodic grid, sampled bilinearly."""

    def __init__(self, texture: Texture, rng: np.random.Generator):
        self.amplitude = texture.amplitude
        self.size = max(int(np.ceil(texture.period * _SAMPLES_PER_LENGTH / texture.length)), 2)
        self.spacing = texture.period / self.size
        self.grid = random_field(rng, self.size, texture.length / self.spacing)

    def __call__(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        column, row = s / self.spacing, t / self.spacing
        c0, r0 = np.floor(column), np.floor(row)
        fc, fr = column - c0, row - r0
        c0 = c0.astype(np.int64) % self.size
        r0 = r0.astype(np.int64) % self.size
        c1, r1 = (c0 + 1) % self.size, (r0 + 1) % self.size
        grid = self.grid
        top = grid[r0, c0] * (1.0 - fc) + grid[r0, c1] * fc
        bottom = grid[r1, c0] * (1.0 - fc) + grid[r1, c1] * fc
        return self.amplitude * (top * (1.0 - fr) + bottom * fr)


class _MaterialMaps:
    """A material with its texture fields drawn."""

    def __init__(self, material: Material, seed: int):
        self.material = material
        self.R0_layers = [
            _Layer(texture, keyed_rng(seed, "texture", material.name, "R0", k))
            for k, texture in enumerate(material.R0_texture)
        ]
        self.n_layers = [
            _Layer(texture, keyed_rng(seed, "texture", material.name, "n", k))
            for k, texture in enumerate(material.n_texture)
        ]

    def __call__(self, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        relative = sum((layer(s, t) for layer in self.R0_layers), np.zeros_like(s))
        offset = sum((layer(s, t) for layer in self.n_layers), np.zeros_like(s))
        return self.material.R0 * (1.0 + relative), self.material.n + offset


def _plane_crossing(start: np.ndarray, along: np.ndarray) -> tuple[np.ndarray, ...]:
    """Where rays cross a planar face's plane, in the face's frame.

    Parameters
    ----------
    start : (3,) ndarray, metres
        The rays' origin relative to the face's centre, along its normal, ``u``, ``v``.
    along : (N, 3) ndarray
        The rays' unit directions along the same axes.

    Returns
    -------
    reach, s, t : (N,) ndarray of float64, metres
        Along the ray to the plane, and the surface coordinates there (inf or
        NaN for rays parallel to the plane).
    facing : (N,) ndarray of bool
        The ray meets the plane's front side.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = -start[0] / along[:, 0]
        hit_s = start[1] + reach * along[:, 1]
        hit_t = start[2] + reach * along[:, 2]
    return reach, hit_s, hit_t, along[:, 0] < 0


def _cylinder_crossings(start: np.ndarray, along: np.ndarray, curvature: float) -> list[tuple[np.ndarray, ...]]:
    """Both crossings of rays with a cylindrical face's cylinder, in the face's frame (:class:`Face`).

    Parameters
    ----------
    start, along
        As in :func:`_plane_crossing`.
    curvature : float, 1/m
        Signed curvature of the face, nonzero.

    Returns
    -------
    list of two (reach, s, t, facing)
        As :func:`_plane_crossing`'s, for each root of the ray-cylinder
        quadratic: ``s`` is the arc length from the line ``s = 0``; NaN where
        the ray misses the cylinder.
    """
    radius = 1.0 / curvature
    sign = np.sign(radius)
    # the ray's origin relative to the axis, and the quadratic |origin + reach along - axis|^2 = radius^2 across it
    normal, side = start[0] + radius, start[1]
    quadratic = along[:, 0] * along[:, 0] + along[:, 1] * along[:, 1]
    half_linear = normal * along[:, 0] + side * along[:, 1]
    constant = normal * normal + side * side - radius * radius
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(half_linear * half_linear - quadratic * constant)
        q = -(half_linear + np.copysign(root, half_linear))  # the stable form of both roots
        crossings = []
        for reach in (q / quadratic, constant / q):
            radial_n = normal + reach * along[:, 0]
            radial_u = side + reach * along[:, 1]
            # outward normal = radial / radius; its angle from the face's normal is s / radius
            facing = sign * (along[:, 0] * radial_n + along[:, 1] * radial_u) < 0
            hit_s = radius * np.arctan2(sign * radial_u, sign * radial_n)
            crossings.append((reach, hit_s, start[2] + reach * along[:, 2], facing))
    return crossings


class Scene:
    """Faces with their materials' textures drawn for one seed.

    Parameters
    ----------
    faces : sequence of Face
        Everything the camera can see.
    seed : int
        Seed of the texture fields; a material's textures depend only on the
        seed and the material's name, so one specimen looks the same in every
        scene it is placed in.
    textures : dict, optional
        Cache of drawn materials shared between scenes of one seed (filled in
        place).
    """

    def __init__(self, faces: Sequence[Face], seed: int, textures: dict | None = None):
        self.faces = tuple(faces)
        textures = {} if textures is None else textures
        for face in self.faces:
            key = (seed, face.material)
            if key not in textures:
                textures[key] = _MaterialMaps(face.material, seed)
        self._maps = [textures[(seed, face.material)] for face in self.faces]
        self._frames = np.stack([np.stack([face.normal, face.u, face.v]) for face in self.faces])
        self._centres = np.stack([face.centre for face in self.faces])
        self._half = np.array([face.half_size for face in self.faces], dtype=np.float64)
        self._curvature = np.array([face.curvature for face in self.faces])

    def trace(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, ...]:
        """Nearest front-facing hit of rays from one origin.

        Parameters
        ----------
        origin : (3,) ndarray, metres
            World point all rays start from.
        directions : (N, 3) ndarray
            Unit directions in the world frame.

        Returns
        -------
        distance : (N,) ndarray of float64, metres
            Along the ray to the hit; inf where nothing is hit.
        face : (N,) ndarray of int64
            Index of the face hit, -1 where nothing is hit.
        s, t : (N,) ndarray of float64, metres
            Surface coordinates of the hit on that face; NaN where nothing is hit.
        """
        count = directions.shape[0]
        distance = np.full(count, np.inf)
        face = np.full(count, -1, dtype=np.int64)
        s = np.full(count, np.nan)
        t = np.full(count, np.nan)
        faces = zip(self._frames, self._centres, self._half, self._curvature)
        for index, (frame, centre, (half_u, half_v), curvature) in enumerate(faces):
            along = directions @ frame.T  # (N, 3): components along normal, u, v
            start = (origin - centre) @ frame.T
            crossings = (
                [_plane_crossing(start, along)] if curvature == 0 else _cylinder_crossings(start, along, curvature)
            )
            for reach, hit_s, hit_t, facing in crossings:
                hit = facing & (reach > 0) & (reach < distance)
                hit &= (np.abs(hit_s) <= half_u) & (np.abs(hit_t) <= half_v)
                distance[hit] = reach[hit]
                face[hit] = index
                s[hit] = hit_s[hit]
                t[hit] = hit_t[hit]
        return distance, face, s, t

    def materials(self, face: np.ndarray, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """R0 and n at surface points.

        Parameters
        ----------
        face : (N,) ndarray of int
            Face index per point, -1 for none.
        s, t : (N,) ndarray, metres
            Surface coordinates on that face.

        Returns
        -------
        R0, n : (N,) ndarray of float64
            NaN where ``face`` is -1.
        """
        R0 = np.full(face.shape, np.nan)
        n = np.full(face.shape, np.nan)
        for index in np.unique(face[face >= 0]):
            on = face == index
            R0[on], n[on] = self._maps[index](s[on], t[on])
        return R0, n

    def normals(self, face: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Outward unit normals at surface points.

        Parameters
        ----------
        face : (N,) ndarray of int
            Face index per point, -1 for none.
        s : (N,) ndarray, metres
            Surface coordinate along ``u`` (arc length on a cylindrical face).

        Returns
        -------
        (N, 3) ndarray of float64
            ``cos(s/r) normal + sin(s/r) u`` (``normal`` on a planar face); NaN
            where ``face`` is -1.
        """
        frames = np.append(self._frames, np.full((1, 3, 3), np.nan), axis=0)[face]
        angle = np.append(self._curvature, np.nan)[face] * s
        return np.cos(angle)[:, None] * frames[:, 0] + np.sin(angle)[:, None] * frames[:, 1]

    def edge_distance(self, face: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Distance of surface points from the nearest edge of their face, along the face.

        Returns
        -------
        (N,) ndarray of float64, metres
            In surface coordinates (arc length across a cylindrical face); inf on
            unbounded faces, NaN where ``face`` is -1.
        """
        half = np.append(self._half, np.full((1, 2), np.nan), axis=0)[face]
        return np.minimum(half[:, 0] - np.abs(s), half[:, 1] - np.abs(t))

    def labels(self, face: np.ndarray) -> np.ndarray:
        """Class index per point: the face's label, -1 where nothing is hit."""
        labels = np.array([f.label for f in self.faces] + [-1], dtype=np.int16)
        return labels[face]


@dataclass(frozen=True, eq=False)
class Geometry:
    """What a camera at one pose sees of a scene, noise-free; all (height, width).

    Attributes
    ----------
    pose : (4, 4) ndarray
        Camera-to-world transform.
    rays : (height, width, 3) ndarray
        Unit viewing rays, camera frame.
    distance : ndarray, metres
        From the camera centre to the surface point; NaN where nothing is hit.
    face : ndarray of int64
        Face index, -1 where nothing is hit.
    s, t : ndarray, metres
        Surface coordinates of the point on its face.
    aoi : ndarray, radians
        Angle of incidence ``arccos(|ray . normal|)``, with the surface's exact
        normal at the point (:meth:`Scene.normals`).
    R0, n : ndarray
        Material at the point.
    label : ndarray of int16
        Class index of specimen top faces, -1 elsewhere.
    edge_distance : ndarray, metres
        Distance along the face from its nearest edge (arc length across a
        cylindrical face; inf if unbounded).
    """

    pose: np.ndarray
    rays: np.ndarray
    distance: np.ndarray
    face: np.ndarray
    s: np.ndarray
    t: np.ndarray
    aoi: np.ndarray
    R0: np.ndarray
    n: np.ndarray
    label: np.ndarray
    edge_distance: np.ndarray

    @property
    def points(self) -> np.ndarray:
        """(height, width, 3) surface points in the camera frame, metres; NaN where nothing is hit."""
        return self.rays * self.distance[..., None]

    def world_points(self) -> np.ndarray:
        """(height, width, 3) surface points in the world frame, metres; NaN where nothing is hit."""
        return world_rays(self.points, self.pose) + self.pose[:3, 3]


def render(scene: Scene, camera: PinholeCamera, pose: np.ndarray) -> Geometry:
    """Cast every pixel's ray into a scene.

    Parameters
    ----------
    scene : Scene
    camera : PinholeCamera
    pose : (4, 4) ndarray
        Camera-to-world transform, metres.

    Returns
    -------
    Geometry
        Noise-free per-pixel geometry and material.
    """
    rays = camera.rays()
    directions = world_rays(rays, pose).reshape(-1, 3)
    distance, face, s, t = scene.trace(pose[:3, 3], directions)
    distance[face < 0] = np.nan
    cosine = np.abs(np.einsum("ij,ij->i", directions, scene.normals(face, s)))
    aoi = np.arccos(np.minimum(cosine, 1.0))
    R0, n = scene.materials(face, s, t)
    shape = camera.shape
    return Geometry(
        pose=np.asarray(pose, dtype=np.float64),
        rays=rays,
        distance=distance.reshape(shape),
        face=face.reshape(shape),
        s=s.reshape(shape),
        t=t.reshape(shape),
        aoi=aoi.reshape(shape),
        R0=R0.reshape(shape),
        n=n.reshape(shape),
        label=scene.labels(face).reshape(shape),
        edge_distance=scene.edge_distance(face, s, t).reshape(shape),
    )


def plane_face(name: str, material: Material, depth: float = 0.0) -> Face:
    """Make an unbounded plane Z = ``depth`` facing the camera (-Z), axes along world X and Y.

    Parameters
    ----------
    name : str
    material : Material
    depth : float, metres
        World Z of the plane.

    Returns
    -------
    Face
        Label -1.
    """
    return Face(
        name=name,
        centre=np.array([0.0, 0.0, depth]),
        u=np.array([1.0, 0.0, 0.0]),
        v=np.array([0.0, 1.0, 0.0]),
        normal=-_EZ,
        half_size=(np.inf, np.inf),
        material=material,
    )


def box_faces(
    name: str,
    centre,
    size: float,
    thickness: float,
    rotation: float,
    material: Material,
    label: int,
    radius: float | None = None,
) -> list[Face]:
    """Make a square specimen raised from the board (Z = 0) towards the camera, its top flat or cylindrical.

    Parameters
    ----------
    name : str
        Prefix of the face names (``<name>.top``, ``<name>.side0`` ..).
    centre : (2,) array_like, metres
        World X, Y of the centre of the top face.
    size : float, metres
        Edge length of the square top face.
    thickness : float, metres
        Height above the board; the top face lies at Z = -thickness.
    rotation : float, radians
        In-plane rotation of the specimen (and its textures) about its centre,
        from world X towards world Y.
    material : Material
        Of all five faces.
    label : int
        Class index of the top face; the sides get -1.
    radius : float or None, metres
        Signed radius of a cylindrical top face (:class:`Face`), bent along its
        ``u`` axis (the rotated world X): positive convex (its edges along the
        axis drop by the sagitta), negative concave (they rise); None flat. The
        top's centre stays at ``thickness`` and its edges ``size`` apart along
        the surface, so the sides along the axis stand at the chord's ends,
        as high as the edges. The two ends (across the axis) are rectangles up
        to the lower of the top's centre and edges: the sliver between them and
        the top's arc, at most the sagitta high, is left open.

    Returns
    -------
    list of Face
        The top face, then the four sides.

    Raises
    ------
    ValueError
        A convex top whose edges would reach the board, or a top bent beyond a half turn.
    """
    top = np.array([centre[0], centre[1], -thickness], dtype=np.float64)
    u = np.array([np.cos(rotation), np.sin(rotation), 0.0])
    v = np.array([-np.sin(rotation), np.cos(rotation), 0.0])
    half = size / 2.0
    top_face = Face(f"{name}.top", top, u, v, -_EZ, (half, half), material, label, radius)
    # half chord, and how far the edges along the axis drop below the top's centre (0 when flat)
    chord, sagitta = half, 0.0
    if radius is not None:
        chord, sagitta = radius * np.sin(half / radius), radius * (1.0 - np.cos(half / radius))
    if sagitta >= thickness:
        raise ValueError(
            f"specimen {name}: a top of radius {radius} m and size {size} m drops {sagitta:.4f} m at its edges, "
            f"more than its thickness {thickness} m; make it thicker or less curved"
        )
    edges, ends = thickness - sagitta, thickness - max(sagitta, 0.0)
    # outward normal, u axis, distance from the top's centre, half extent along u, height above the board
    sides = [
        (u, v, chord, half, edges),
        (-u, -v, chord, half, edges),
        (v, -u, half, chord, ends),
        (-v, u, half, chord, ends),
    ]
    faces = [top_face]
    for k, (outward, along, offset, extent, height) in enumerate(sides):
        faces.append(
            Face(
                name=f"{name}.side{k}",
                centre=top + offset * outward + (thickness - 0.5 * height) * _EZ,
                u=along,
                v=_EZ,
                normal=outward,
                half_size=(extent, height / 2.0),
                material=material,
            )
        )
    return faces
