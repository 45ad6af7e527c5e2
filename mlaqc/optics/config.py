"""Camera configuration: main lens, MLA, sensor, geometry and sensor model, read from TOML and validated.

The paper's Table 1 camera is the default (also shipped as fixtures/paper_table1.toml). Geometry left
unset defaults to the f-number-matched setting (DESIGN.md §2): the MLA sits where the main lens'
exit pupil (diameter D) subtends the same angle as a microlens (p/f), so sub-images fill their cells.
Every error names the offending key, e.g. "config key 'mla.pitch_um' must be positive, got -3".
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from mlaqc.errors import InputError
from mlaqc.optics import datasheet
from mlaqc.optics.lattice import PACKINGS, Lattice
from mlaqc.optics.paraxial import ThickLens, image_distance, thick_lens

CFA_CHOICES = ("none", "RGGB", "BGGR", "GRBG", "GBRG")
CORNER_CHOICES = ("opaque", "clear")
BOUNDARY_CHOICES = ("grid", "sag-intersection")
APERTURE_CHOICES = ("cell", "circle")
GAP_CHOICES = ("opaque", "clear")
ENGINE_CHOICES = ("auto", "numba", "numpy")
SAMPLER_CHOICES = ("sobol", "random")


@dataclass(frozen=True)
class MainLens:
    """The main lens: a thick biconvex lens by its surfaces (the paper's; its rim (diameter) is the aperture
    stop), or an ideal imaging system by its datasheet numbers (mlaqc.optics.datasheet): the image-side
    `f_number`, or an objective's `magnification` and `na` with the `tube_lens_mm` in use (its
    `design_tube_lens_mm`, default 200 mm), and `exit_pupil_mm`, the exit pupil's distance before the MLA
    (inf: image-side telecentric, the objective's default). The thick-lens keys then do not apply."""

    diameter_mm: float = 42.0
    thickness_mm: float = 14.5
    radius_front_mm: float = 106.0
    radius_back_mm: float = -106.0
    refractive_index: float = 1.5168
    f_number: float | None = None
    magnification: float | None = None
    na: float | None = None
    tube_lens_mm: float | None = None
    design_tube_lens_mm: float | None = None
    exit_pupil_mm: float | None = None

    @property
    def ideal(self) -> bool:
        """An ideal imaging system given by datasheet numbers, not a thick lens traced through its surfaces."""
        return self.f_number is not None


@dataclass(frozen=True)
class MLA:
    """The microlens array; radii follow the optical sign convention.

    `packing`: 'square' or 'hex' (mlaqc.optics.lattice: U(m,n) row m from the top, column n from the
    left; on hex, rows are pitch*sqrt(3)/2 apart and even rows m = 2, 4, ... are shifted +pitch/2).

    `aperture`: 'cell' (100 % fill: each lens fills its square or hexagonal cell) or 'circle' (a round
    lens of `aperture_diameter_um` centred on its front vertex, moving with it; between the circles is
    flat substrate, `gap` 'opaque' (a black mask) or 'clear' (light passes undeviated)).

    `corners`: where the two spherical surfaces would cross (beyond r ≈ 68 µm for Table 1) there is no
    lens. 'opaque' blocks those rays (a black matrix); 'clear' lets them pass undeviated.

    `boundaries`: which lens a ray belongs to. 'sag-intersection' (default, the physical model): a
    replicated 100 %-fill array, where each lens ends where its sag meets its neighbours' sags (a ray
    enters the front sphere it meets first and leaves the rear sphere it meets last; see
    mlaqc.optics.raytrace). 'grid': an idealised array whose lens is that of the design-grid cell a hit
    point lies in (a pitch error moves the surfaces, not the cell's square or hexagonal aperture), for idealised studies; on
    it a pitch error and a decenter cannot be told apart (inspection reports them as 'position').

    `focal_length_um` and `profile` ('plano-convex': convex side towards the main lens, flat back; or
    'biconvex', symmetric) describe the lens as sold; the radii are then derived (datasheet.mla_radii_um)
    and `mla.thickness_um` is the vertex thickness (substrate included).

    `black_matrix_um`: width of an opaque mask centred on the design cells' edges (grid lines; hexagon
    sides on hex) in the front vertex plane (0 = none); rays crossing that plane within half the width of
    an edge are absorbed.

    Width: on hex the sensor must hold `count_w` pitches (the unshifted rows); the shifted rows' end
    lenses may hang half a pitch over it and are then read as clipped.
    """

    count_w: int = 102
    count_h: int = 102
    pitch_um: float = 100.0
    packing: str = "square"
    aperture: str = "cell"
    aperture_diameter_um: float | None = None  # required with aperture = 'circle'
    gap: str = "opaque"
    radius_front_um: float = 469.0
    radius_back_um: float = -469.0
    thickness_um: float = 10.0
    refractive_index: float = 1.56
    corners: str = "opaque"
    boundaries: str = "sag-intersection"
    black_matrix_um: float = 0.0
    focal_length_um: float | None = None
    profile: str | None = None
    counts_auto: bool = False  # count_w / count_h given as "auto": the lenses the sensor sees (COUNT_AUTO)

    @property
    def flat_sided(self) -> bool:
        """A surface is flat (plano-convex): shifting it against the other (a decenter) changes nothing."""
        return math.isinf(self.radius_front_um) or math.isinf(self.radius_back_um)


@dataclass(frozen=True)
class Relay:
    """Relay optics between the MLA's focal plane and the sensor (two camera lenses nose to nose, a 50:35
    pair...): `magnification` (> 0; the frame as stored, upright) and the relay's working `f_number` on the
    MLA side. 1 with no f-number: no relay."""

    magnification: float = 1.0
    f_number: float | None = None

    @property
    def present(self) -> bool:
        return self.magnification != 1.0 or self.f_number is not None


@dataclass(frozen=True)
class Sensor:
    """Pixel array and its photon-to-DN model (QE, full well, gain, black level, noise, CFA)."""

    pixel_um: float = 5.0
    width_px: int = 2048
    height_px: int = 2048
    bit_depth: int = 12
    qe: float = 0.6
    full_well_e: float = 20000.0
    gain_dn_per_e: float = 0.2
    black_level_dn: int = 64
    read_noise_e: float = 3.0
    cfa: str = "none"
    cfa_qe: tuple[float, float, float] = (0.45, 0.6, 0.4)  # QE of R, G, B sites when a CFA is set
    exposure_photons: float = 20000.0  # photons per pixel at relative irradiance 1 (white scene)


@dataclass(frozen=True)
class Geometry:
    """Distances along the axis; None means 'derive from the f-number-matched setting'.

    object_distance_mm: object plane to the main lens' front vertex.
    mla_distance_mm: main lens' rear vertex to the MLA mid-plane.
    sensor_gap_um: MLA rear vertex to the sensor (None: the microlens back focal distance).
    image_defocus_mm: an ideal main lens (datasheet numbers) only: it images the scene's plane this far before
      the MLA's mid-plane (negative: behind it; None: on it, the scene in focus). Such a scene is given by its
      image: point positions in mm in that plane, a texture over the MLA's extent there, upright.
    """

    object_distance_mm: float | None = None
    mla_distance_mm: float | None = None
    sensor_gap_um: float | None = None
    wavelength_nm: float = 632.8
    image_defocus_mm: float | None = None


@dataclass(frozen=True)
class Trace:
    """Ray-tracer settings."""

    fresnel: bool = True
    rays_per_pixel: float = 50.0
    batch_rays: int = 1 << 18
    threads: int = 0  # 0 = one per CPU core
    engine: str = "auto"  # 'numba' (compiled fast path), 'numpy' (reference), 'auto' = numba if installed
    sampler: str = "sobol"  # 'sobol' (low-discrepancy, stratified per microlens), 'random' (plain Monte-Carlo)


@dataclass(frozen=True)
class Formation:
    """Sensor-side image formation the geometric tracer leaves out (mlaqc.optics.formation): applied by
    `simulate` before read-out; each can be switched off so that geometry can be tested alone."""

    diffraction: bool = True  # convolve with the microlens aperture's Fraunhofer PSF at geometry.wavelength_nm
    crosstalk: float = 0.02  # fraction of a pixel's charge that reaches each of its 4 neighbours
    prnu_rms: float = 0.005  # pixel response non-uniformity, relative rms (a fixed pattern of the sensor)
    prnu_seed: int = 7  # the sensor's PRNU pattern


@dataclass(frozen=True)
class QC:
    """QC spec: per-type limits a flagged lens must stay within, and what fails the array."""

    pitch_um: float = 1.0
    decenter_um: float = 5.0
    radius_rel: float = 0.05
    tilt_deg: float = 2.0
    thickness_um: float = 3.0
    dim_rel: float = 0.1  # a dim lens' transmission loss (relative; its sub-image keeps its shape)
    obscuration_area: float = 0.1  # a local obscuration's (dust, residue, dig) share of the sub-image's disc
    scratch_area: float = 0.05  # a scratch's (a dark line through the sub-image) share of the sub-image's disc
    detect_sigma: float = 6.0  # robust z-score above which a lens is flagged (noise peaks near 4.7 over 10,404 lenses)
    max_out_of_tolerance: int = 0  # more than this many out-of-tolerance lenses fails the array
    max_missing: int = 0  # more than this many missing lenses fails the array
    report_fraction: float = 0.4  # the smallest error reported, as a fraction of its tolerance (physical floor)
    # bounds on the array's assembly readings (mlaqc.inspection.assembly), absolute values; None: not bounded
    assembly_distance_um: float | None = None  # MLA-sensor gap change from design
    assembly_rotation_deg: float | None = None  # MLA rotation about the optical axis
    assembly_tilt_deg: float | None = None  # each of the MLA's two tilts
    assembly_shift_um: float | None = None  # each component of the MLA centre's offset from the sensor centre


@dataclass(frozen=True)
class CameraConfig:
    """The whole camera: one object passed to the tracer, the pipeline and written to every sidecar."""

    main_lens: MainLens = field(default_factory=MainLens)
    mla: MLA = field(default_factory=MLA)
    sensor: Sensor = field(default_factory=Sensor)
    geometry: Geometry = field(default_factory=Geometry)
    trace: Trace = field(default_factory=Trace)
    qc: QC = field(default_factory=QC)
    formation: Formation = field(default_factory=Formation)
    relay: Relay = field(default_factory=Relay)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (TOML/JSON-able) of the config as given, geometry holes left as None. The datasheet
        keys (DATASHEET_KEYS) and the relay appear only when used, so a config written before them keeps
        its dict (and the content hashes of its cached models)."""
        d = asdict(self)
        for sec, keys in DATASHEET_KEYS.items():
            for key in keys:
                if d[sec][key] is None:
                    del d[sec][key]
        if not self.relay.present:
            del d["relay"]
        if self.mla.counts_auto:  # written as given: derived again from the sensor when read
            d["mla"]["count_w"] = d["mla"]["count_h"] = "auto"
        del d["mla"]["counts_auto"]
        if self.main_lens.ideal:  # the thick lens' defaults do not describe it
            for key in THICK_MAIN_KEYS:
                del d["main_lens"][key]
        return d

    @property
    def pixel_at_mla_um(self) -> float:
        """The size of one sensor pixel in the MLA's focal plane: the pixel over the relay's magnification."""
        return self.sensor.pixel_um / self.relay.magnification if self.relay.present else self.sensor.pixel_um

    @property
    def layout(self) -> Layout:
        """Axial positions and first-order facts derived from the config."""
        return compute_layout(self)


@dataclass(frozen=True)
class Layout:
    """Derived axial layout in mm (z = 0 at the main lens' front vertex, light along +z)."""

    main: ThickLens | None  # None: an ideal main lens (datasheet numbers)
    micro: ThickLens  # in mm
    object_distance_mm: float
    mla_distance_mm: float
    sensor_gap_mm: float
    z_object_mm: float
    z_mla_mm: float  # MLA mid-plane
    z_sensor_mm: float
    pupil_to_mla_mm: float  # main lens rear principal plane (an ideal lens: its exit pupil) to MLA mid-plane (b)
    subimage_pitch_px: float  # p*(b+f)/b / pixel
    z_exit_mm: float  # where image-side rays start: the thick lens' rear vertex, an ideal lens' exit pupil
    exit_radius_mm: float  # and the radius of that disc
    image_f_number: float  # the main lens' image-side working f-number at the MLA
    z_scene_mm: float  # where a scene's radiance is looked up: the object plane, or an ideal lens' image of it


# keys that exist only for datasheet-described optics (left out of to_dict while unset)
DATASHEET_KEYS = {"main_lens": ("f_number", "magnification", "na", "tube_lens_mm", "design_tube_lens_mm",
                                "exit_pupil_mm"),
                  "mla": ("focal_length_um", "profile"), "geometry": ("image_defocus_mm",)}


def compute_layout(cfg: CameraConfig) -> Layout:
    """Fill geometry holes: matched b = D*f/p; object and MLA conjugate through the main lens."""
    ml, mla, geo = cfg.main_lens, cfg.mla, cfg.geometry
    micro = thick_lens(mla.radius_front_um * 1e-3, mla.radius_back_um * 1e-3, mla.thickness_um * 1e-3, mla.refractive_index)
    if ml.ideal:
        return _ideal_layout(cfg, micro)
    main = thick_lens(ml.radius_front_mm, ml.radius_back_mm, ml.thickness_mm, ml.refractive_index)
    h_front, h_rear = main.front_principal, main.rear_principal
    if geo.mla_distance_mm is None and geo.object_distance_mm is None:
        b = ml.diameter_mm * micro.efl / (mla.pitch_um * 1e-3)
        a = image_distance(main.efl, b)
    elif geo.mla_distance_mm is None:
        a = geo.object_distance_mm + h_front
        b = image_distance(main.efl, a)
    else:
        b = geo.mla_distance_mm + h_rear
        a = geo.object_distance_mm + h_front if geo.object_distance_mm is not None else image_distance(main.efl, b)
    gap_mm = micro.bfd if geo.sensor_gap_um is None else geo.sensor_gap_um * 1e-3
    z_mla = ml.thickness_mm + b - h_rear
    z_sensor = z_mla + 0.5 * mla.thickness_um * 1e-3 + gap_mm
    lens_to_sensor = z_sensor - z_mla
    return Layout(
        main=main,
        micro=micro,
        object_distance_mm=a - h_front,
        mla_distance_mm=b - h_rear,
        sensor_gap_mm=gap_mm,
        z_object_mm=-(a - h_front),
        z_mla_mm=z_mla,
        z_sensor_mm=z_sensor,
        pupil_to_mla_mm=b,
        subimage_pitch_px=mla.pitch_um * (b + lens_to_sensor) / b / cfg.pixel_at_mla_um,
        z_exit_mm=ml.thickness_mm,
        exit_radius_mm=0.5 * ml.diameter_mm,
        image_f_number=b / ml.diameter_mm,
        z_scene_mm=-(a - h_front),
    )


def _ideal_layout(cfg: CameraConfig, micro: ThickLens) -> Layout:
    """An ideal main lens: its exit pupil at z = 0, the MLA `exit_pupil_mm` behind it (a telecentric one's
    far away, datasheet.TELECENTRIC_PUPIL_MM), no object distance: every scene is traced from the image side
    and given by its image, `geometry.image_defocus_mm` before the MLA."""
    ml, mla, geo = cfg.main_lens, cfg.mla, cfg.geometry
    b = datasheet.traced_pupil_mm(ml.exit_pupil_mm)
    gap_mm = micro.bfd if geo.sensor_gap_um is None else geo.sensor_gap_um * 1e-3
    lens_to_sensor = 0.5 * mla.thickness_um * 1e-3 + gap_mm
    return Layout(main=None, micro=micro, object_distance_mm=math.inf, mla_distance_mm=b, sensor_gap_mm=gap_mm,
                  z_object_mm=-math.inf, z_mla_mm=b, z_sensor_mm=b + lens_to_sensor, pupil_to_mla_mm=b,
                  subimage_pitch_px=mla.pitch_um * (b + lens_to_sensor) / b / cfg.pixel_at_mla_um,
                  z_exit_mm=0.0, exit_radius_mm=datasheet.pupil_radius_mm(b, ml.f_number),
                  image_f_number=ml.f_number, z_scene_mm=b - (geo.image_defocus_mm or 0.0))


def default_config() -> CameraConfig:
    """The paper's Table 1 camera at the f-number-matched geometry."""
    return CameraConfig()


def load_config(path: str | Path | None) -> CameraConfig:
    """Read and validate a TOML camera config; None gives the default. Raises InputError."""
    if path is None:
        return default_config()
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise InputError(f"config file {str(p)!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"config file {str(p)!r} cannot be read ({exc.__class__.__name__})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
    return config_from_dict(data, source=str(p))


# the keys that may be infinite (a telecentric exit pupil, a flat surface): strict JSON (report.json) has
# no infinity and writes them as null
INFINITE_KEYS = frozenset({"main_lens.exit_pupil_mm", "mla.radius_front_um", "mla.radius_back_um"})


def config_from_strict_json(data: dict[str, Any], source: str = "config") -> CameraConfig:
    """A config as a strict-JSON file (a report's) holds it: INFINITE_KEYS written as null read as inf."""
    fixed = {sec: ({k: (math.inf if v is None and f"{sec}.{k}" in INFINITE_KEYS else v) for k, v in table.items()}
                   if isinstance(table, dict) else table) for sec, table in data.items()}
    return config_from_dict(fixed, source)


def config_from_dict(data: dict[str, Any], source: str = "config") -> CameraConfig:
    """Build a validated CameraConfig from nested dicts (the TOML tables)."""
    sections = {f.name: f.type for f in fields(CameraConfig)}
    unknown = set(data) - set(sections)
    if unknown:
        raise InputError(f"{source}: unknown config section {sorted(unknown)[0]!r}; expected one of {sorted(sections)}")
    base = CameraConfig()
    parts = {}
    for name in sections:
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise InputError(f"{source}: config key {name!r} must be a table")
        if name == "mla":
            table = _auto_counts_marked(table, source)
        parts[name] = _build_section(getattr(base, name), table, name, source)
    parts["main_lens"] = _resolve_main_lens(parts["main_lens"], data.get("main_lens", {}), source)
    parts["mla"] = _resolve_mla(parts["mla"], data.get("mla", {}), source)
    cfg = CameraConfig(**parts)
    if cfg.mla.counts_auto:
        cfg = replace(cfg, mla=replace(cfg.mla, **_counts_seen(cfg)))
    validate(cfg, source)
    return cfg


COUNT_AUTO = "auto"


def _auto_counts_marked(table: dict[str, Any], source: str) -> dict[str, Any]:
    """The [mla] table with count_w / count_h = "auto" taken out and `counts_auto` set (both go together:
    a frame that sees part of the array sees it in both directions)."""
    if "counts_auto" in table:
        raise InputError(f"{source}: unknown config key 'mla.counts_auto'; write count_w = count_h = \"auto\"")
    auto = [k for k in ("count_w", "count_h") if table.get(k) == COUNT_AUTO]
    if not auto:
        return table
    if len(auto) == 1:
        other = "count_h" if auto[0] == "count_w" else "count_w"
        raise InputError(f"{source}: config key 'mla.{other}' must be \"auto\" too when 'mla.{auto[0]}' is: "
                         "the lenses a frame holds are counted in both directions")
    out = {k: v for k, v in table.items() if k not in auto}
    out["counts_auto"] = True
    return out


def _counts_seen(cfg: CameraConfig) -> dict[str, int]:
    """count_w / count_h for "auto": an array centred on the axis whose sub-images cover the whole sensor
    with at least half a sub-image to spare on every side (the MLA larger than the sensor, as in a
    microscope or a cropped region of interest: the frame's border lenses are cut)."""
    mla, s = cfg.mla, cfg.sensor
    pitch_px = compute_layout(replace(cfg, mla=replace(mla, count_w=1, count_h=1))).subimage_pitch_px
    row_px = pitch_px * (math.sqrt(3.0) / 2.0 if mla.packing == "hex" else 1.0)
    return {"count_w": math.ceil(s.width_px / pitch_px) + 2, "count_h": math.ceil(s.height_px / row_px) + 2}


THICK_MAIN_KEYS = ("diameter_mm", "thickness_mm", "radius_front_mm", "radius_back_mm", "refractive_index")


def _resolve_main_lens(ml: MainLens, given: dict[str, Any], source: str) -> MainLens:
    """An ideal main lens from its datasheet numbers: the objective form converted to the image-side
    f-number; keys of the two descriptions mixed, or an f-number that the objective contradicts, refused."""
    ideal = [k for k in DATASHEET_KEYS["main_lens"] if k in given]
    if not ideal:
        return ml
    thick = [k for k in THICK_MAIN_KEYS if k in given]
    if thick:
        raise InputError(f"{source}: config key 'main_lens.{thick[0]}' describes a thick main lens, but "
                         f"'main_lens.{ideal[0]}' an ideal one: give the lens' surfaces or its datasheet numbers, not both")
    if (ml.magnification is None) != (ml.na is None):
        key = "na" if ml.na is None else "magnification"
        raise InputError(f"{source}: config key 'main_lens.{key}' is needed: an objective is given by its "
                         f"magnification and numerical aperture together")
    if ml.na is None:
        for key in ("tube_lens_mm", "design_tube_lens_mm"):
            _require(getattr(ml, key) is None, source, f"main_lens.{key}", "only applies to an objective "
                     "(main_lens.magnification and main_lens.na)", getattr(ml, key))
        _require(ml.f_number is not None, source, "main_lens.f_number",
                 "is needed: an ideal main lens is given by its image-side f-number (or an objective's "
                 "magnification and na)", ml.f_number)
        _require(ml.exit_pupil_mm is not None, source, "main_lens.exit_pupil_mm",
                 "is needed with main_lens.f_number: the exit pupil's distance before the MLA in mm (inf: "
                 "image-side telecentric)", ml.exit_pupil_mm)
        return ml
    for key in ("magnification", "na", "tube_lens_mm", "design_tube_lens_mm"):
        v = getattr(ml, key)
        _require(v is None or (math.isfinite(v) and v > 0), source, f"main_lens.{key}", "must be positive", v)
    _require(ml.na < ml.magnification, source, "main_lens.na", "must be below the magnification (the image-side "
             "NA is na / magnification < 1)", ml.na)
    obj = datasheet.objective(ml.magnification, ml.na, ml.tube_lens_mm, ml.design_tube_lens_mm)
    if ml.f_number is not None and abs(ml.f_number / obj.f_number - 1.0) > datasheet.F_NUMBER_AGREEMENT:
        raise InputError(f"{source}: config key 'main_lens.f_number' ({ml.f_number:g}) contradicts the objective: "
                         f"{obj.magnification:g}x / NA {ml.na:g} makes the image side f/{obj.f_number:.4g}; give one or the other")
    return replace(ml, f_number=obj.f_number)


def _resolve_mla(mla: MLA, given: dict[str, Any], source: str) -> MLA:
    """An MLA by its focal length and profile: the radii derived; radii also given must be those."""
    if mla.focal_length_um is None:
        _require(mla.profile is None, source, "mla.profile", "only applies with mla.focal_length_um", mla.profile)
        return mla
    f = mla.focal_length_um
    _require(math.isfinite(f) and f > 0, source, "mla.focal_length_um", "must be positive", f)
    profile = mla.profile or "plano-convex"
    _require(profile in datasheet.PROFILES, source, "mla.profile", f"must be one of {datasheet.PROFILES}", profile)
    _require(mla.refractive_index > 1, source, "mla.refractive_index", "must be greater than 1", mla.refractive_index)
    _require(mla.thickness_um > 0, source, "mla.thickness_um", "must be positive", mla.thickness_um)
    try:
        front, back = datasheet.mla_radii_um(f, mla.refractive_index, mla.thickness_um, profile)
    except ValueError as exc:
        raise InputError(f"{source}: config key 'mla.thickness_um' does not fit mla.focal_length_um: {exc}") from None
    for key, derived in (("radius_front_um", front), ("radius_back_um", back)):
        if key in given and not math.isclose(getattr(mla, key), derived, rel_tol=1e-9):
            raise InputError(f"{source}: config key 'mla.{key}' ({getattr(mla, key):g}) contradicts mla.focal_length_um "
                             f"= {f:g} µm ({profile}: {derived:.6g} µm); give the radii or the focal length, not both")
    return replace(mla, radius_front_um=front, radius_back_um=back, profile=profile)


def _build_section(default: Any, table: dict[str, Any], section: str, source: str) -> Any:
    """Overlay a TOML table on a section's defaults, checking key names and value types."""
    known = {f.name: f for f in fields(default)}
    values = {}
    for key, value in table.items():
        if key not in known:
            raise InputError(f"{source}: unknown config key '{section}.{key}'; expected one of {sorted(known)}")
        values[key] = _coerce(getattr(default, key), value, f"{section}.{key}", source, known[key].type)
    return replace(default, **values)


def _coerce(default: Any, value: Any, key: str, source: str, type_text: Any) -> Any:
    """Check one value's type against its default's; ints are accepted for floats."""
    optional = "None" in str(type_text)
    if value is None and optional:  # JSON null: a derived geometry value
        return None
    if isinstance(default, bool) or "bool" in str(type_text):
        if not isinstance(value, bool):
            raise InputError(f"{source}: config key '{key}' must be true or false, got {value!r}")
        return value
    if isinstance(default, int) and not isinstance(default, bool) and "int" in str(type_text):
        if not isinstance(value, int) or isinstance(value, bool):
            raise InputError(f"{source}: config key '{key}' must be an integer, got {value!r}")
        return value
    if default is None and "str" in str(type_text):
        if not isinstance(value, str):
            raise InputError(f"{source}: config key '{key}' must be a string, got {value!r}")
        return value
    if isinstance(default, float) or (default is None and optional):
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise InputError(f"{source}: config key '{key}' must be a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise InputError(f"{source}: config key '{key}' must be a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list) or len(value) != len(default) or not all(isinstance(v, (int, float)) for v in value):
            raise InputError(f"{source}: config key '{key}' must be a list of {len(default)} numbers, got {value!r}")
        return tuple(float(v) for v in value)
    raise InputError(f"{source}: config key '{key}' has an unsupported value {value!r}")


def _require(ok: bool, source: str, key: str, what: str, value: Any) -> None:
    if not ok or (isinstance(value, float) and not math.isfinite(value)):
        raise InputError(f"{source}: config key '{key}' {what}, got {value!r}")


def validate(cfg: CameraConfig, source: str = "config") -> None:
    """Check that the camera is physically possible; raise InputError naming the first bad key."""
    ml, mla, s, g, t = cfg.main_lens, cfg.mla, cfg.sensor, cfg.geometry, cfg.trace
    flat_ok = INFINITE_KEYS
    for sec, obj in (("main_lens", ml), ("mla", mla), ("sensor", s), ("geometry", g), ("qc", cfg.qc), ("relay", cfg.relay)):
        for f in fields(obj):
            v = getattr(obj, f.name)
            if isinstance(v, float) and not (f"{sec}.{f.name}" in flat_ok and v == math.inf):
                _require(math.isfinite(v), source, f"{sec}.{f.name}", "must be a finite number", v)
    _require(math.isfinite(mla.radius_front_um) or math.isfinite(mla.radius_back_um), source, "mla.radius_front_um",
             "and mla.radius_back_um are both flat: the microlens has no power", mla.radius_front_um)
    if ml.ideal:
        _validate_ideal(cfg, source)
    else:
        _validate_thick(cfg, source)
    for key in ("count_w", "count_h"):
        _require(getattr(mla, key) >= 1, source, f"mla.{key}", "must be at least 1", getattr(mla, key))
    for key in ("pitch_um", "thickness_um"):
        _require(getattr(mla, key) > 0, source, f"mla.{key}", "must be positive", getattr(mla, key))
    _require(mla.refractive_index > 1, source, "mla.refractive_index", "must be greater than 1", mla.refractive_index)
    _require(mla.packing in PACKINGS, source, "mla.packing", f"must be one of {PACKINGS}", mla.packing)
    _require(mla.aperture in APERTURE_CHOICES, source, "mla.aperture", f"must be one of {APERTURE_CHOICES}", mla.aperture)
    _require(mla.gap in GAP_CHOICES, source, "mla.gap", f"must be one of {GAP_CHOICES}", mla.gap)
    if mla.aperture == "circle":
        d = mla.aperture_diameter_um
        _require(d is not None and 0 < d <= mla.pitch_um, source, "mla.aperture_diameter_um",
                 f"must be set, positive and at most the pitch {mla.pitch_um} µm with aperture = 'circle'", d)
        reach, what = 0.5 * d, "the aperture's radius"
    else:
        _require(mla.aperture_diameter_um is None, source, "mla.aperture_diameter_um",
                 "is only used with aperture = 'circle'", mla.aperture_diameter_um)
        reach = mla.pitch_um / (math.sqrt(3) if mla.packing == "hex" else math.sqrt(2))
        what = "the cell's circumradius" if mla.packing == "hex" else "the cell's half-diagonal"
    for key in ("radius_front_um", "radius_back_um"):
        r = getattr(mla, key)
        if math.isinf(r):  # a flat surface covers any aperture
            continue
        _require(r != 0 and abs(r) > reach, source, f"mla.{key}",
                 f"must exceed {what} {reach:.1f} µm in magnitude so the surface covers the aperture", r)
    _require(mla.corners in CORNER_CHOICES, source, "mla.corners", f"must be one of {CORNER_CHOICES}", mla.corners)
    _require(mla.boundaries in BOUNDARY_CHOICES, source, "mla.boundaries", f"must be one of {BOUNDARY_CHOICES}", mla.boundaries)
    _require(0 <= mla.black_matrix_um < mla.pitch_um, source, "mla.black_matrix_um",
             f"must be in [0, pitch {mla.pitch_um} µm)", mla.black_matrix_um)
    for key in ("pixel_um",):
        _require(getattr(s, key) > 0, source, f"sensor.{key}", "must be positive", getattr(s, key))
    for key in ("width_px", "height_px"):
        _require(getattr(s, key) >= 8, source, f"sensor.{key}", "must be at least 8", getattr(s, key))
    _validate_relay(cfg, source)
    pix = cfg.pixel_at_mla_um
    seen = " (as the relay images it)" if cfg.relay.present else ""
    _require(mla.counts_auto or mla.count_w * mla.pitch_um <= s.width_px * pix, source, "mla.count_w",
             f"makes the MLA ({mla.count_w * mla.pitch_um / 1000:.3f} mm) wider than the sensor{seen} ({s.width_px * pix / 1000:.3f} mm)", mla.count_w)
    height_um = Lattice(mla.packing, mla.count_h, mla.count_w, mla.pitch_um).extent[1]
    _require(mla.counts_auto or height_um <= s.height_px * pix, source, "mla.count_h",
             f"makes the {mla.packing} MLA ({height_um / 1000:.3f} mm) taller than the sensor{seen} ({s.height_px * pix / 1000:.3f} mm)", mla.count_h)
    _require(8 <= s.bit_depth <= 16, source, "sensor.bit_depth", "must be between 8 and 16", s.bit_depth)
    _require(0 < s.qe <= 1, source, "sensor.qe", "must be in (0, 1]", s.qe)
    _require(all(0 < q <= 1 for q in s.cfa_qe), source, "sensor.cfa_qe", "must hold three values in (0, 1]", s.cfa_qe)
    for key in ("full_well_e", "gain_dn_per_e", "exposure_photons"):
        _require(getattr(s, key) > 0, source, f"sensor.{key}", "must be positive", getattr(s, key))
    _require(s.read_noise_e >= 0, source, "sensor.read_noise_e", "must not be negative", s.read_noise_e)
    _require(0 <= s.black_level_dn < 2 ** s.bit_depth, source, "sensor.black_level_dn", f"must be in [0, {2 ** s.bit_depth})", s.black_level_dn)
    _require(s.cfa in CFA_CHOICES, source, "sensor.cfa", f"must be one of {CFA_CHOICES}", s.cfa)
    for key in ("pitch_um", "decenter_um", "radius_rel", "tilt_deg", "thickness_um", "dim_rel", "obscuration_area",
                "scratch_area", "detect_sigma", "report_fraction"):
        _require(getattr(cfg.qc, key) > 0, source, f"qc.{key}", "must be positive", getattr(cfg.qc, key))
    fm = cfg.formation
    _require(math.isfinite(fm.crosstalk) and 0 <= fm.crosstalk < 0.2, source, "formation.crosstalk", "must be in [0, 0.2)", fm.crosstalk)
    _require(math.isfinite(fm.prnu_rms) and 0 <= fm.prnu_rms < 0.2, source, "formation.prnu_rms", "must be in [0, 0.2)", fm.prnu_rms)
    for key in ("assembly_distance_um", "assembly_rotation_deg", "assembly_tilt_deg", "assembly_shift_um"):
        v = getattr(cfg.qc, key)
        _require(v is None or (math.isfinite(v) and v > 0), source, f"qc.{key}", "must be positive", v)
    for key in ("max_out_of_tolerance", "max_missing"):
        _require(getattr(cfg.qc, key) >= 0, source, f"qc.{key}", "must not be negative", getattr(cfg.qc, key))
    _require(t.rays_per_pixel > 0, source, "trace.rays_per_pixel", "must be positive", t.rays_per_pixel)
    _require(1024 <= t.batch_rays <= 1 << 24, source, "trace.batch_rays", "must be between 1024 and 16777216", t.batch_rays)
    _require(t.engine in ENGINE_CHOICES, source, "trace.engine", f"must be one of {ENGINE_CHOICES}", t.engine)
    _require(t.sampler in SAMPLER_CHOICES, source, "trace.sampler", f"must be one of {SAMPLER_CHOICES}", t.sampler)
    _require(0 <= t.threads <= 256, source, "trace.threads", "must be between 0 and 256", t.threads)
    for key in ("object_distance_mm", "mla_distance_mm", "sensor_gap_um"):
        v = getattr(g, key)
        _require(v is None or v > 0, source, f"geometry.{key}", "must be positive", v)
    _require(g.wavelength_nm > 0, source, "geometry.wavelength_nm", "must be positive", g.wavelength_nm)
    if not ml.ideal:
        _require(g.image_defocus_mm is None, source, "geometry.image_defocus_mm", "applies to an ideal main lens "
                 "(main_lens.f_number or na); a thick one's scene is placed by geometry.object_distance_mm",
                 g.image_defocus_mm)
        _validate_thick_geometry(cfg, source)


def _validate_thick(cfg: CameraConfig, source: str) -> None:
    """The thick main lens' surfaces: positive sizes, radii that cover the rim, a positive edge."""
    ml = cfg.main_lens
    for key in ("diameter_mm", "thickness_mm"):
        _require(getattr(ml, key) > 0, source, f"main_lens.{key}", "must be positive", getattr(ml, key))
    _require(ml.refractive_index > 1, source, "main_lens.refractive_index", "must be greater than 1", ml.refractive_index)
    for key in ("radius_front_mm", "radius_back_mm"):
        r = getattr(ml, key)
        _require(r != 0 and abs(r) > ml.diameter_mm / 2, source, f"main_lens.{key}",
                 f"must exceed the lens' half-diameter {ml.diameter_mm / 2} mm in magnitude", r)
    edge = ml.thickness_mm - _sag(ml.radius_front_mm, ml.diameter_mm / 2) + _sag(ml.radius_back_mm, ml.diameter_mm / 2)
    _require(edge > 0, source, "main_lens.thickness_mm", f"gives a negative edge thickness ({edge:.3f} mm) at the rim", ml.thickness_mm)


def _validate_thick_geometry(cfg: CameraConfig, source: str) -> None:
    """Object and MLA distances through a thick main lens: a real image, nothing inside the lens."""
    ml, g = cfg.main_lens, cfg.geometry
    if g.object_distance_mm is not None and g.mla_distance_mm is None:
        main = thick_lens(ml.radius_front_mm, ml.radius_back_mm, ml.thickness_mm, ml.refractive_index)
        _require(g.object_distance_mm + main.front_principal > main.efl, source, "geometry.object_distance_mm",
                 f"must put the object beyond the front focal length ({main.ffd:.2f} mm) so a real image forms", g.object_distance_mm)
    lay = compute_layout(cfg)
    _require(lay.mla_distance_mm > 0, source, "geometry.mla_distance_mm", "puts the MLA inside the main lens", lay.mla_distance_mm)
    _require(lay.object_distance_mm > 0, source, "geometry.object_distance_mm", "puts the object inside the main lens", lay.object_distance_mm)


def _validate_ideal(cfg: CameraConfig, source: str) -> None:
    """An ideal main lens: a possible f-number, a pupil in front of the MLA, no thick-lens distances."""
    ml, g = cfg.main_lens, cfg.geometry
    _require(ml.f_number >= 0.5, source, "main_lens.f_number", "must be at least 0.5 (sin u' <= 1)", ml.f_number)
    _require(ml.exit_pupil_mm is None or ml.exit_pupil_mm > 0, source, "main_lens.exit_pupil_mm",
             "must be positive (the exit pupil's distance before the MLA; inf: telecentric)", ml.exit_pupil_mm)
    for key in ("object_distance_mm", "mla_distance_mm"):
        _require(getattr(g, key) is None, source, f"geometry.{key}", "applies to a thick main lens; an ideal one "
                 "(main_lens.f_number or na) is placed by main_lens.exit_pupil_mm", getattr(g, key))
    pupil_mm = datasheet.traced_pupil_mm(ml.exit_pupil_mm)
    _require(g.image_defocus_mm is None or g.image_defocus_mm < pupil_mm, source, "geometry.image_defocus_mm",
             f"must put the scene's image behind the exit pupil ({pupil_mm:g} mm before the MLA)", g.image_defocus_mm)


def _validate_relay(cfg: CameraConfig, source: str) -> None:
    """A relay's magnification, and an f-number fast enough to pass the microlenses' light unclipped (the
    model's relay is unvignetted): the cone a lens' whole aperture sends to its focal plane."""
    r, mla = cfg.relay, cfg.mla
    _require(r.magnification > 0, source, "relay.magnification", "must be positive (the frame as stored, upright)",
             r.magnification)
    if r.f_number is None:
        return
    _require(r.f_number > 0, source, "relay.f_number", "must be positive", r.f_number)
    if mla.aperture == "circle":
        reach_um = 0.5 * (mla.aperture_diameter_um or mla.pitch_um)
    else:
        reach_um = mla.pitch_um / (math.sqrt(3) if mla.packing == "hex" else math.sqrt(2))
    f_um = thick_lens(mla.radius_front_um, mla.radius_back_um, mla.thickness_um, mla.refractive_index).efl
    needed = f_um / (2.0 * reach_um)
    _require(r.f_number <= needed, source, "relay.f_number",
             f"would clip the light the microlenses send to their focal plane (it needs f/{needed:.3g} or faster; "
             "mlaqc models an unvignetted relay)", r.f_number)


def _sag(radius: float, rho: float) -> float:
    """Sag of a sphere of signed `radius` at height `rho` (same sign as the radius)."""
    return radius - math.copysign(math.sqrt(radius * radius - rho * rho), radius)


def config_to_toml(cfg: CameraConfig) -> str:
    """Serialize a config as TOML (holes in the geometry are omitted, so they stay 'matched')."""
    lines: list[str] = []
    for sec, table in cfg.to_dict().items():
        lines.append(f"[{sec}]")
        for key, value in table.items():
            if value is None:
                continue
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def require_thick_main_lens(cfg: CameraConfig, what: str) -> None:
    """Refuse, in one sentence, work that traces the object side through the main lens' surfaces when the
    main lens is an ideal one given by datasheet numbers (its scenes are traced from its exit pupil)."""
    if cfg.main_lens.ideal:
        raise InputError(f"{what} needs the object side traced through the main lens' surfaces; this config gives "
                         "an ideal main lens (main_lens.f_number / na), which is traced from its exit pupil only (white, "
                         "point and texture scenes, placed by geometry.image_defocus_mm): describe the lens by "
                         "main_lens.radius_front_mm, radius_back_mm, thickness_mm, diameter_mm and refractive_index for it")
