"""The ``correspond`` stage: every carriage's marked points in the photos, automatic (SIFT) and manual.

Reads the photos of the set (``camera.photos``), their intrinsics (the incident's ``cameras.json``, else
``out/georef/cameras.json``, else the camera profile, else EXIF or a default focal), the consist, and the
incident's hand-written ``correspondences.json`` (validated). Writes ``out/correspond/correspondences.json``
(docs/pipeline.md): the automatic observations, with every manual one replacing the automatic one of the
same (carriage, point, view), and the carriages that need manual points. Pixels are those of the photos as
they are on disk (distorted), docs/conventions.md.

Per photo: SIFT features of the undistorted photo; per car (its own livery) and planar face, a homography
by RANSAC; the detections are assigned to the cars jointly (:mod:`.assign`); the marked points on a face's
plane are transferred by its (refined) homography, the others (couplers, corners) projected from the
face's pose. Face references are written to ``out/correspond/references/`` for review (and the picker).

The automatic finder runs only where it can work: with ``[correspond] finder = "auto"`` (the default) and for
the cars whose type has reference imagery (``CarriageType.has_reference_imagery``: a livery that is the car's
real appearance). The other cars are listed as needing manual points, with the reason; when no car is left to
search, no photo is scanned. With ``finder = "off"`` no photo is scanned at all: the output holds the
incident's hand picks, and every car without one is listed as needing manual points.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.settings import FinderMode
from ..core.stage_api import Progress, StageResult
from ..errors import InputError
from ..files.intrinsics import photo_size, resolve_intrinsics
from ..project import Project
from . import cache, prefetch
from ..files import correspondences as mf
from .assign import find_cars, observations_of
from .ground import Ground
from .match import MatchOptions, PhotoFeatures, photo_features
from .undistort import undistortion_maps
from .parallel import STEPS, PhotoResult, default_workers, map_photos
from .references import FACES, build_references, face_reference
from .search import chain_search
from .transfer import PairHomographies, carry

log = logging.getLogger(__name__)
REFERENCE_THREADS = 2  # the cars' references are built on this many threads


def output_path(project: Project) -> Path:
    return project.stage_dir("correspond") / mf.FILE_NAME


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read this photo ({exc})") from None


def photo_intrinsics(project: Project, photos: list[Path]) -> tuple[dict[str, CameraIntrinsics], str]:
    """Intrinsics of each photo (name -> CameraIntrinsics of the photo as on disk) and where they came from."""
    sizes = {p.name: photo_size(p) for p in photos}
    cameras = project.cameras()
    if cameras is not None:
        if all(n in cameras for n in sizes):
            return {n: cameras[n].intrinsics for n in sizes}, project.relative(cameras.path)
        log.warning("%s does not list every photo of the set; using the camera profile", cameras.path)
    prof = project.camera_profile()
    if prof is not None:
        return {n: prof.for_size(w, h) for n, (w, h) in sizes.items()}, project.relative(prof.path)
    choice = resolve_intrinsics(project, photos)  # EXIF, SfM or the fallback (the solve estimates its focal)
    return choice.per_photo, choice.source


def camera_poses(project: Project, photos: list[Path]) -> dict[str, np.ndarray]:
    """cam_from_world (4, 4) of each photo listed in ``cameras.json`` (the incident's or georef's); {} without."""
    cameras = project.cameras()
    if cameras is None:
        return {}
    names = {p.name for p in photos}
    return {v.name: v.cam_from_world for v in cameras.views if v.name in names}


def _terrain(project: Project):
    """The incident's terrain model (None without a DEM)."""
    if not project.settings.terrain.dem:
        return None
    try:
        return project.terrain_model()
    except InputError as exc:
        log.warning("correspond: no terrain for the pose search (%s)", exc)
        return None


def load_manual(project: Project, photos: list[Path] | None = None) -> mf.CorrespondenceFile:
    """The incident's manual correspondences (empty if there is no file), validated against the incident."""
    path = project.manual_picks_path
    if not path.is_file():
        return mf.CorrespondenceFile()
    types = project.carriage_types()
    photos = photos if photos is not None else project.photo_paths()
    sizes = {p.name: photo_size(p) for p in photos}
    pano = project.stage_dir("stitch") / "panorama.jpg"
    if pano.is_file():
        sizes[mf.PANORAMA] = photo_size(pano)
    return mf.load(path, points={n: list(t.marked_points) for n, t in types.items()}, image_sizes=sizes)


def _cached_references(project: Project, ct, number: str, opts: MatchOptions, cache_dir: Path | None,
                       used: set[str]) -> tuple[list, list]:
    """The car's face references with their features (:func:`references.build_references`), and those of its
    faces that are only aligned (the roof: no features), from the cache (``cache.py``) when it holds them."""

    def build():
        rs = build_references(ct, number, px_per_m=opts.px_per_m, tilts=opts.tilts, end_tilts=opts.end_tilts)
        have = {r.face for r in rs}
        return rs, [face_reference(ct, number, f, opts.px_per_m) for f in FACES if f not in have]

    if cache_dir is None:
        return build()
    name = "references_" + cache.key("references", ct.id, ct.spec.model_dump_json(), number, opts.px_per_m,
                                     opts.tilts, opts.end_tilts, FACES) + ".npz"
    used.add(name)
    hit = cache.load(cache_dir / name)
    if hit is not None:
        try:
            return (cache.references_from_arrays(hit, ct.id, number),
                    cache.references_from_arrays(hit, ct.id, number, prefix="aligned_"))
        except (KeyError, ValueError, IndexError) as exc:
            log.info("cache entry %s unusable (%s); computed again", name, exc)
    rs, aligned = build()
    cache.save(project, cache_dir / name, {**cache.references_to_arrays(rs),
                                           **cache.references_to_arrays(aligned, prefix="aligned_")})
    return rs, aligned


def _photo_cache_name(path: Path, K: CameraIntrinsics, opts: MatchOptions) -> str:
    return "photo_" + cache.key("photo", cache.file_digest(path), repr(K), opts.photo_upsample,
                                opts.max_photo_side_px) + ".npz"


def _cached_photo_features(project: Project, path: Path, K: CameraIntrinsics, opts: MatchOptions,
                           cache_file: Path | None) -> PhotoFeatures:
    """:func:`match.photo_features` of the photo, from the cache (``cache.py``) when it holds them."""
    if cache_file is not None:
        hit = cache.load(cache_file)
        if hit is not None and {"gray", "keypoints", "descriptors", "frames"} <= set(hit):
            return PhotoFeatures(path.name, K, hit["gray"], hit["keypoints"], hit["descriptors"], hit["frames"])
    pf = photo_features(path.name, _read_rgb(path), K, opts)
    if cache_file is not None:
        _save_features(project, cache_file, pf)
    return pf


def _save_features(project: Project, entry: Path, pf: PhotoFeatures) -> None:
    """A photo's features written to their cache entry (what :func:`_cached_photo_features` reads)."""
    cache.save(project, entry, {"gray": pf.gray_undistorted, "keypoints": pf.keypoints,
                                "descriptors": pf.descriptors, "frames": pf.frames})


def prefetch_features(project: Project) -> None:
    """``StageSpec.prefetch``: the photos' features computed into the cache ahead of the stage, in a forked process,
    while the stages before it run (``prefetch.py``), under the names the stage will read them by if georef gives
    the photos the intrinsics known now. Only where those are fixed before the run (a calibrated camera on the
    panorama or single-photo route, or the incident's own cameras): where the stitch or SfM estimate them, georef
    gives other intrinsics and the work would be lost. Nothing when no photo will be scanned."""
    source = project.settings.camera.source.value
    fixed = project.own_cameras_path.is_file() or (source == "calibrated" and project.settings.camera.profile)
    if not fixed or source == "sfm" or _not_searched(project)[1] is not None:
        return
    photos = project.photo_paths()
    opts = MatchOptions()
    intrinsics, _ = photo_intrinsics(project, photos)
    cache_dir = project.stage_dir("correspond") / "cache"
    files = {p.name: cache_dir / _photo_cache_name(p, intrinsics[p.name], opts) for p in photos}

    def compute(p: Path) -> None:
        _save_features(project, files[p.name], photo_features(p.name, _read_rgb(p), intrinsics[p.name], opts))

    prefetch.start(photos, files, compute)


FINDER_OFF_REASON = ("the automatic finder is off (project.toml: [correspond] finder = 'off'); pick its points by "
                     "hand (workbench pick)")


def no_reference_reason(type_id: str) -> str:
    """Why a car of type ``type_id`` is not searched for (:attr:`CarriageType.has_reference_imagery` false)."""
    return (f"type {type_id!r} has no reference imagery (a mesh type, no [livery], or livery.reference = false): "
            f"the automatic finder does not search for it; pick its points by hand (workbench pick)")


def _car_references(project: Project, consist: list[tuple], types: dict, opts: MatchOptions, progress: Progress,
                    reference_dir: Path | None, cache_dir: Path | None, cache_used: set[str]
                    ) -> tuple[dict[str, list], dict, list[str]]:
    """Every searched car's face references (number -> list; the cars whose type has reference imagery),
    those of faces aligned only (``ref_cache``: (number, face) -> reference) and the cars without texture
    enough to match; the references written to ``reference_dir`` (images and ``references.json``) for review."""
    ref_cache: dict = {}  # built here once: the workers inherit them
    refs = {}
    untextured = []
    ref_doc = {}
    searched = [number for number, _, _ in consist if types[number].has_reference_imagery]
    # the cars' references on two threads (painting the livery and SIFT over the tilts release the interpreter
    # much of the time; each car's are computed as alone), used in the consist's order
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=REFERENCE_THREADS) as pool:
        built = pool.map(lambda n: _cached_references(project, types[n], n, opts, cache_dir, cache_used), searched)
        for k, (number, (rs, aligned)) in enumerate(zip(searched, built)):
            progress(0.05 * k / len(searched), f"references of {number}")
            _keep_references(project, number, rs, aligned, opts, refs, ref_cache, untextured, ref_doc, reference_dir)
    if reference_dir is not None:
        project.write_json(reference_dir / "references.json", ref_doc)
    return refs, ref_cache, untextured


def _keep_references(project: Project, number: str, rs: list, aligned: list, opts: MatchOptions, refs: dict,
                     ref_cache: dict, untextured: list, ref_doc: dict, reference_dir: Path | None) -> None:
    """One car's references kept (``refs``, ``ref_cache``, ``untextured``) and written for review."""
    for r in aligned:  # references of faces aligned only (the roof), shared by the photos
        ref_cache[(number, r.face)] = r
    textured = [r for r in rs if r.descriptors is not None and len(r.descriptors) >= opts.min_reference_keypoints]
    if not textured:
        untextured.append(number)
    refs[number] = rs
    if reference_dir is not None:
        for r in rs:
            img_path = reference_dir / f"{number}_{r.face}.png"
            project.write_image(img_path, r.image)
            ref_doc.setdefault(number, {})[r.face] = {
                "image": project.relative(img_path), "type": r.type_id, "px_per_m": r.px_per_m,
                "n_keypoints": int(len(r.keypoints)), "points": {n: p.tolist() for n, p in r.points.items()},
                "origin_m": r.origin_m.tolist(), "axis_u_m": r.axis_u_m.tolist(), "axis_v_m": r.axis_v_m.tolist()}


class _PhotoMatcher:
    """The work on one photo, in two tasks (``parallel.map_photos``, in forked workers that inherit this):
    ``features`` computes the photo's features into ``photo_file`` (the cache, else a folder of this run);
    ``match`` reads them back, finds the cars (SIFT, then the chain/terrain pose search where the photo has a
    camera pose) and their marked points."""

    def __init__(self, project: Project, intrinsics: dict[str, CameraIntrinsics], opts: MatchOptions,
                 photo_file: dict[str, Path], refs: dict[str, list] | None, ref_cache: dict | None,
                 consist: list[tuple], types: dict, poses: dict[str, np.ndarray], terrain, carry_on: bool,
                 cache_dir: Path | None = None):
        self.project, self.intrinsics, self.opts, self.photo_file = project, intrinsics, opts, photo_file
        self.consist, self.types, self.cache_dir = consist, types, cache_dir
        self.poses, self.terrain, self.carry_on = poses, terrain, carry_on
        self.refs: dict[str, list] | None = None
        if refs is not None:
            self.use_references(refs, ref_cache or {})

    def use_references(self, refs: dict[str, list], ref_cache: dict) -> None:
        self.refs, self.ref_cache = refs, ref_cache
        self.by_number = {n: {r.face: r for r in rs} for n, rs in refs.items()}

    def _references(self) -> None:
        """The cars' references in a worker forked before the parent built them: read from the cache, where the
        parent wrote them before it queued any photo's second task (the same arrays as a rerun reads)."""
        refs, ref_cache = {}, {}
        for number, _, _ in self.consist:
            ct = self.types[number]
            if not ct.has_reference_imagery:
                continue
            rs, aligned = _cached_references(self.project, ct, number, self.opts, self.cache_dir, set())
            refs[number] = rs
            ref_cache.update({(number, r.face): r for r in aligned})
        self.use_references(refs, ref_cache)

    def features(self, p: Path, note) -> float:
        t0 = time.perf_counter()
        f = self.photo_file[p.name]
        prefetch.wait_for(p.name, f)  # being computed ahead of the stage: its entry, once written
        if f.is_file():
            note("features", "features computed by the features process" if prefetch.took(p.name)
                 else "features from the cache")
        else:
            note("features", f"{self.compute_features(p)} features")
        return time.perf_counter() - t0

    def compute_features(self, p: Path) -> int:
        """The photo's features computed and written to its entry; returns how many."""
        pf = photo_features(p.name, _read_rgb(p), self.intrinsics[p.name], self.opts)
        _save_features(self.project, self.photo_file[p.name], pf)
        return len(pf.keypoints)

    def match(self, p: Path, note, t_features: float) -> PhotoResult:
        opts, consist, types = self.opts, self.consist, self.types
        t0 = time.perf_counter() - t_features
        if self.refs is None:
            self._references()
        # (an entry that cannot be read, or could not be written, is computed here)
        pf = _cached_photo_features(self.project, p, self.intrinsics[p.name], opts, self.photo_file[p.name])
        ground = None
        if self.terrain is not None and p.name in self.poses:  # a one-face pose's branch judged on the terrain too
            ground = Ground(self.poses[p.name], self.terrain, self.project.settings.terrain.dem_vertical_accuracy_m)
        found = find_cars(pf, self.refs, consist, types, opts, self.ref_cache, ground)
        note("cars", f"faces of {len({c.number for c in found})} cars found")
        searched = None
        if opts.search and p.name in self.poses:
            before = {c.number for c in found}
            found = chain_search(pf, found, consist, types, self.by_number, self.poses[p.name], self.terrain, opts,
                                 self.ref_cache)
            searched = sorted({c.number for c in found} - before)
        note("search", "pose search done" if searched is not None else "no pose search (no camera pose)")
        points = observations_of(found, pf, types, pose_points=opts.pose_points)
        stats = {"keypoints": int(len(pf.keypoints)), "time_s": round(time.perf_counter() - t0, 2),
                 "faces": [{"carriage": c.number, "face": c.detection.ref.face,
                            "inliers": c.detection.n_inliers, "support": c.support,
                            "rms_px": round(c.detection.rms_px, 2), "guided": c.detection.guided,
                            "branch": c.branch,
                            "ecc": None if c.detection.ecc is None else round(c.detection.ecc, 3)}
                           for c in found],
                 "points": len(points),
                 "cars_by_pose_search": searched}
        note("done", f"{len(points)} points")
        return PhotoResult(p.name, points, stats, pf.keypoints if self.carry_on else None,
                           pf.descriptors if self.carry_on else None)


def _match_photos(matcher: _PhotoMatcher, photos: list[Path], intrinsics: dict[str, CameraIntrinsics],
                  opts: MatchOptions, progress: Progress, carry_on: bool, references=None
                  ) -> tuple[list[PhotoResult], dict[str, PhotoFeatures], PairHomographies | None]:
    """Every photo matched on worker processes: the results, in the photos' order, and, to carry points between
    the photos of a panorama set, their features and the homographies between them. ``references()``: builds the
    cars' references (into the cache, where the workers read them) once the workers are computing the photos'
    features. A photo whose features the prefetch (``prefetch.py``) computes, or will (it took the photos on:
    ``prefetch.adopt``), is held back (``map_photos(hold=...)``) until the prefetch has written them (then it goes
    ahead of the matches not queued yet), so that one process computes them all; at niceness 19 the prefetch
    gets a core once a worker has nothing else to do, and where it gets none then (a loaded machine) the
    photos are the workers' (``prefetch.owns``)."""
    steps_done: set = set()

    def report(index: int, step: str, message: str) -> None:
        steps_done.add((index, step))
        progress(0.05 + 0.9 * len(steps_done) / (len(STEPS) * max(len(photos), 1)),
                 f"{photos[index].name}: {message}")

    # a worker's memory peaks in SIFT on the resized photo, about 270 bytes per pixel there (3.2 GB measured at
    # 4000 x 3000), on top of the photo itself at full size, decoded and undistorted (about 14 bytes per pixel:
    # 3.4-4.0 GB measured on 81 MP photos, docs/stitching.md "Large photos")
    per_worker = max([270.0 * min(opts.photo_upsample, opts.max_photo_side_px / max(K.width, K.height)) ** 2
                      * K.width * K.height + 14.0 * K.width * K.height
                      for K in (intrinsics[p.name] for p in photos)] or [0.0])
    workers = opts.workers or default_workers(per_worker)
    # one process computes every photo's features (prefetch.py): the run's prefetch where it computes the entries
    # read here, else one started now, where the photos go to several workers and two or more are not computed yet
    todo = [p for p in photos if not matcher.photo_file[p.name].is_file()]
    if not prefetch.adopt(matcher.photo_file) and min(workers, len(photos)) > 1 and len(todo) > 1:
        prefetch.finish()  # (a run's prefetch of other entries, which adopt stopped)
        prefetch.start(todo, {p.name: matcher.photo_file[p.name] for p in todo},
                       matcher.compute_features, ahead=False)
        prefetch.adopt(matcher.photo_file)

    def before_second() -> None:
        if references is not None:
            references()
        if photos:
            progress(0.05, f"matching {len(photos)} photos on {min(workers, len(photos))} processes")
    # kept only to carry points between the photos of a panorama set; the homographies between them are
    # computed in the photos' order as soon as both photos of a pair are done, while the others are matched
    features: dict[str, PhotoFeatures] = {}
    pairs = PairHomographies([p.name for p in photos]) if carry_on else None

    def features_done(index: int, _token) -> None:
        # a photo's features, read back from where its first task wrote them (the arrays its second task reads):
        # the pairs with it are computed while the photos are matched, not after the last one
        name = photos[index].name
        hit = cache.load(matcher.photo_file[name]) if pairs is not None else None
        if hit is not None and {"keypoints", "descriptors"} <= set(hit):
            features[name] = PhotoFeatures(name, intrinsics[name], None, hit["keypoints"], hit["descriptors"])
            pairs.advance(features)

    def done(index: int, r: PhotoResult) -> None:
        if r.keypoints is not None and r.name not in features:
            features[r.name] = PhotoFeatures(r.name, intrinsics[r.name], None, r.keypoints, r.descriptors)
        if pairs is not None:
            pairs.advance(features)

    def computed_ahead(index: int, idle: bool) -> bool:
        name = photos[index].name
        return prefetch.owns(name, matcher.photo_file[name], idle)

    results = map_photos(matcher.match, photos, workers, report, on_result=done, first=matcher.features,
                         on_first=features_done, before_second=before_second, hold=computed_ahead)
    features = {r.name: features[r.name] for r in results if r.name in features}  # in the photos' order
    return results, features, pairs


def automatic(project: Project, photos: list[Path], intrinsics: dict[str, CameraIntrinsics], opts: MatchOptions,
              progress: Progress, reference_dir: Path | None = None,
              cache_dir: Path | None = None) -> tuple[list[mf.Observation], list[dict], dict]:
    """SIFT observations of every photo, the carriages needing manual points, and statistics.

    ``cache_dir``: where the references and the photos' features are kept between runs (``cache.py``;
    None: computed every time)."""
    s = project.settings
    types = project.carriage_types()
    consist = [(c.number, types[c.number].id, c.coupling_to_next.value if c.coupling_to_next else None)
               for c in s.consist]
    cache_used: set[str] = set()
    carry_on = opts.carry_between_photos and len(photos) > 1 and s.camera.source.value != "sfm"
    # the chain/terrain pose search needs each photo's camera in the scene frame, and uses the terrain
    poses = camera_poses(project, photos) if opts.search else {}
    terrain = _terrain(project) if poses else None

    # each photo's features are computed by a first task and written here (the cache, else a folder of this
    # run), where the photo's second task reads them (parallel.map_photos)
    work_dir = cache_dir if cache_dir is not None else Path(tempfile.mkdtemp(prefix="correspond-"))
    photo_file = {}
    for p in photos:
        photo_file[p.name] = work_dir / _photo_cache_name(p, intrinsics[p.name], opts)
        cache_used.add(photo_file[p.name].name)
    for p in photos:  # the undistortion maps of the photos still to do, once per camera (the workers inherit them)
        K = intrinsics[p.name]
        if not photo_file[p.name].is_file() and K.has_distortion:
            undistortion_maps(K, K.width, K.height)
    matcher = _PhotoMatcher(project, intrinsics, opts, photo_file, None, None, consist, types, poses, terrain,
                            carry_on, cache_dir)
    built: dict = {}

    def references() -> None:
        # the cars' references (SIFT over the tilts of every face), built here while the workers compute the
        # photos' features; written to the cache, where workers forked before read them (with no cache, the
        # references are built first and the workers inherit them)
        built["refs"], built["ref_cache"], built["untextured"] = _car_references(
            project, consist, types, opts, progress, reference_dir, cache_dir, cache_used)
        matcher.use_references(built["refs"], built["ref_cache"])

    if cache_dir is None:
        references()
    try:
        results, features, pairs = _match_photos(matcher, photos, intrinsics, opts, progress, carry_on,
                                                 references if cache_dir is not None else None)
    finally:
        prefetch.finish()
        if cache_dir is None:
            shutil.rmtree(work_dir, ignore_errors=True)
    if "refs" not in built:  # no photo: nothing matched, the references still listed
        references()
    refs, untextured = built["refs"], built["untextured"]
    if len(untextured) == len(refs):  # nothing to match against: no photo's result counts
        results, features, pairs, carry_on = [], {}, None, False
    obs: list[mf.Observation] = []
    per_view = {r.name: r.points for r in results}
    per_photo = {r.name: r.stats for r in results}
    if cache_dir is not None:
        cache.prune(cache_dir, cache_used)
    carried_stats = None
    if carry_on:
        progress(0.95, "carrying points between the photos of the panorama")
        per_view, carried_stats = carry(per_view, features, pairs=pairs)
    for name, pts in per_view.items():
        for o in pts:
            al = None if o.loading is None else mf.Alignment(
                loading_px=[[round(float(x), 5) for x in row] for row in o.loading], n_matches=o.n_matches)
            obs.append(mf.Observation(carriage=o.carriage, point=o.point, view=o.view, uv=o.uv, source="sift",
                                      confidence=o.confidence, sigma_px=o.sigma_px, method=o.how,
                                      face=o.face, alignment=al,
                                      ecc=None if o.ecc is None else round(float(o.ecc), 4)))
    needs = [{"carriage": n, "reason": "reference has no texture (too few features on every face); pick its "
                                       "points by hand"} for n in untextured]
    seen = {o.carriage for o in obs}
    needs += [{"carriage": n, "reason": "no face matched in any photo"} for n, _, _ in consist
              if n not in seen and n not in untextured and n in refs]
    needs += [{"carriage": n, "reason": no_reference_reason(t)} for n, t, _ in consist if n not in refs]
    return obs, needs, {"photos": per_photo, "carried": carried_stats}


def _not_searched(project: Project) -> tuple[list[dict], str | None]:
    """The cars the automatic finder will not search for, with the reason, and why no photo is scanned at all
    (None: the finder runs)."""
    s = project.settings
    if s.correspond.finder is FinderMode.OFF:
        return [{"carriage": c.number, "reason": FINDER_OFF_REASON} for c in s.consist], "finder off"
    types = project.carriage_types()
    needs = [{"carriage": c.number, "reason": no_reference_reason(types[c.number].id)} for c in s.consist
             if not types[c.number].has_reference_imagery]
    return needs, ("no type with reference imagery" if len(needs) == len(s.consist) else None)


def run_correspond(project: Project, progress: Progress, opts: MatchOptions | None = None) -> StageResult:
    opts = opts or MatchOptions()
    photos = project.photo_paths()
    man = load_manual(project, photos)  # validate first: a bad file fails before minutes of matching
    out_dir = project.stage_dir("correspond")
    skipped, no_scan = _not_searched(project)
    outputs = {}
    if no_scan is None:
        intrinsics, intr_source = photo_intrinsics(project, photos)
        auto, needs, stats = automatic(project, photos, intrinsics, opts, progress,
                                       reference_dir=out_dir / "references", cache_dir=out_dir / "cache")
        outputs["references"] = out_dir / "references" / "references.json"
    else:  # nothing to search for: no photo is read but for its size (the picks' check)
        intr_source, auto, needs, stats = None, [], skipped, {"photos": {}, "carried": None}
        shutil.rmtree(out_dir / "references", ignore_errors=True)  # an earlier automatic run's: not this one's
        log.info("correspond: no photo scanned (%s); the hand picks only", no_scan)
    stats["finder"] = project.settings.correspond.finder.value
    stats["not_searched"] = [n["carriage"] for n in skipped]
    merged = mf.merge(auto, man.observations, man.rejected)
    manual_cars = {o.carriage for o in man.observations}
    needs = [n for n in needs if n["carriage"] not in manual_cars]
    known = {n["carriage"] for n in needs}
    needs += [n.model_dump() for n in man.needs_manual if n.carriage not in known and n.carriage not in manual_cars]
    doc = mf.CorrespondenceFile(observations=merged, needs_manual=[mf.NeedsManual(**n) for n in needs])
    path = project.write_json(output_path(project), doc.to_json())
    overridden = len({o.key for o in auto} & {o.key for o in man.observations})
    rejected = len({o.key for o in auto} & {r.key for r in man.rejected})
    by_car: dict[str, int] = {}
    for o in merged:
        by_car[o.carriage] = by_car.get(o.carriage, 0) + 1
    stats.update({"intrinsics": intr_source, "n_observations": len(merged), "n_sift": len(auto),
                  "n_manual": len(man.observations), "n_overridden": overridden,
                  "n_rejected": rejected, "by_carriage": by_car,
                  "needs_manual": needs, "options": {k: getattr(opts, k) for k in opts.__dataclass_fields__}})
    for n in needs:
        log.warning("carriage %s needs manual points: %s", n["carriage"], n["reason"])
    return StageResult(outputs={"correspondences": path, **outputs}, stats=stats)


__all__ = ["run_correspond", "load_manual", "photo_intrinsics", "automatic", "no_reference_reason", "FACES",
           "prefetch_features"]
