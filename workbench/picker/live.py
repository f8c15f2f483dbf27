"""A carriage's pose while its points are being picked: where its remaining marked points should fall.

``POST /api/pose`` with ``{"carriage": "6100", "observations": [{"point", "view", "uv"[, "sigma_px"]}, ...],
"view": "pano_01.jpg"}`` (the car's current picks, saved or not) answers :func:`live_pose`. Nothing is written.

The start is the solver's own SQPnP (:func:`workbench.solve.pnp.pnp`) in the photo with most picks; with an
unknown focal it is run over the solver's focal grid (:func:`workbench.solve.focal.focal_grid`, the field-of-view
range of ``solver.hfov_range_deg``) and the focal of least reprojection error kept. Then every photo's picks
refine the pose together (and each unknown focal), by Gauss-Newton with Levenberg damping on the solver's
projection and its analytic Jacobian (:func:`workbench.solve.projection.project_with_jacobians`), each pick
weighed by its sigma (``solver.pixel_sigma_px``, or its own ``sigma_px`` when larger).

A pose needs :data:`MIN_POINTS_KNOWN` picks in one photo whose focal is known (solved, or given as known in
``cameras.json``), or :data:`MIN_POINTS_UNKNOWN` where it is estimated, and the picked points must not lie on
one line of the carriage (nor their pixels on one line of the photo). With more picks than the pose needs, each
pick is checked against the pose **the other picks** give (leave one out: a wrong pick drags a least-squares
pose towards itself, and spreads its error over the right ones): the pick farthest from where the others put it,
in sigmas (its own and the prediction's together), is flagged when beyond
:data:`workbench.picker.overlay.FLAG_SIGMAS` and left out of the pose, and the check repeats on the rest while
more picks than the pose needs are left. Every marked point's predicted pixel carries its standard deviation from
the pose's covariance (the largest axis of its 2 x 2 covariance).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.geometry import exp_so3
from ..errors import InputError
from ..files.correspondences import cut_for_message
from ..project import Project
from ..solve.focal import focal_grid
from ..solve.pnp import pnp
from ..solve.projection import project_with_jacobians
from .geometry import in_sight, model_edges, outline, project_points
from .overlay import FLAG_SIGMAS, PickerCamera, picker_cameras

MIN_POINTS_KNOWN = 4
MIN_POINTS_UNKNOWN = 6
FOCAL_STEP_RATIO = 1.03
MAX_OBSERVATIONS = 5000
REQUEST_KEYS = ("carriage", "observations", "view")
OBSERVATION_KEYS = ("point", "view", "uv", "sigma_px")


def _number(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_request(payload: object, points: dict[str, list[str]],
                  sizes: dict[str, tuple[int, int]]) -> tuple[str, list, str | None]:
    """``(carriage, [(point, view, (u, v), sigma or None)], view)`` of a pose request; :class:`InputError`
    naming the key and the value otherwise. ``points``: car number -> its marked points; ``sizes``: photo name ->
    (width, height): a pick lies inside its photo, as in a save."""
    if not isinstance(payload, dict):
        raise InputError(f'a pose request is a JSON object {{"carriage", "observations", "view"}}; got '
                         f"{type(payload).__name__}")
    bad = [k for k in payload if k not in REQUEST_KEYS]
    if bad:
        raise InputError(f"unknown key {cut_for_message(bad[0])} in the pose request (its keys: carriage, "
                         f"observations, view)")
    car = payload.get("carriage")
    if car not in points:
        raise InputError(f"carriage = {cut_for_message(car)}: not a carriage of the consist")
    view = payload.get("view")
    if view is not None and view not in sizes:
        raise InputError(f"view = {cut_for_message(view)}: not a photo of the incident")
    obs = payload.get("observations")
    if not isinstance(obs, list) or len(obs) > MAX_OBSERVATIONS:
        raise InputError(f"observations = {cut_for_message(obs)}: must be a list of at most {MAX_OBSERVATIONS} objects")
    out, seen = [], set()
    for i, o in enumerate(obs):
        where = f"observations[{i}]"
        if not isinstance(o, dict):
            raise InputError(f"{where} = {cut_for_message(o)}: must be an object {{point, view, uv}}")
        extra = [k for k in o if k not in OBSERVATION_KEYS]
        if extra:
            raise InputError(f"{where}: unknown key {cut_for_message(extra[0])} (its keys: point, view, uv, sigma_px)")
        if o.get("point") not in points[car]:
            raise InputError(f"{where}.point = {cut_for_message(o.get('point'))}: not a marked point of car {car}")
        if o.get("view") not in sizes:
            raise InputError(f"{where}.view = {cut_for_message(o.get('view'))}: not a photo of the incident")
        uv = o.get("uv")
        if not (isinstance(uv, list) and len(uv) == 2 and all(_number(x) for x in uv)):
            raise InputError(f"{where}.uv = {cut_for_message(uv)}: must be two finite numbers [u, v]")
        w, h = sizes[o["view"]]
        if not (-0.5 <= uv[0] <= w - 0.5 and -0.5 <= uv[1] <= h - 0.5):
            raise InputError(f"{where}.uv = {cut_for_message(uv)}: outside view {cut_for_message(o['view'])} "
                             f"({w} x {h} px)")
        sig = o.get("sigma_px")
        if sig is not None and not (_number(sig) and sig > 0):
            raise InputError(f"{where}.sigma_px = {cut_for_message(sig)}: must be a positive number of pixels")
        key = (o["point"], o["view"])
        if key in seen:
            raise InputError(f"{where}: point {cut_for_message(o['point'])} in view {cut_for_message(o['view'])} "
                             f"is given twice")
        seen.add(key)
        out.append((o["point"], o["view"], (float(uv[0]), float(uv[1])), None if sig is None else float(sig)))
    return car, out, view


def degenerate(P: np.ndarray, uv: np.ndarray) -> str | None:
    """Why points ``P`` (carriage frame, m) seen at ``uv`` cannot fix a pose, or None: on one line of the car,
    or seen on one line of the photo."""
    def flat(X: np.ndarray, floor: float) -> bool:
        s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        return s[0] <= floor or s[1] <= max(floor, 0.02 * s[0])

    if flat(np.asarray(P, float), 0.05):
        return "the picked points lie on one line of the carriage"
    if flat(np.asarray(uv, float), 1.0):
        return "the picks lie on one line of the photo"
    return None


class _Fit:
    """The least-squares fit of one carriage's pose (and the unknown focals ``free_f``) to picks ``rows``
    ``(point, view, P (3,), uv (2,), sigma)``."""

    def __init__(self, rows: list, cams: dict[str, PickerCamera], free_f: list[str]):
        self.rows, self.cams, self.free_f = rows, cams, free_f
        self.n_par = 6 + len(free_f)

    def project(self, rows: list, R, t, f: dict[str, float]):
        """Pixels (n, 2) of ``rows`` and d pixel / d parameters (n, 2, n_par)."""
        uv = np.empty((len(rows), 2))
        J = np.zeros((len(rows), 2, self.n_par))
        for v in sorted({r[1] for r in rows}):
            idx = [i for i, r in enumerate(rows) if r[1] == v]
            cam = self.cams[v]
            intr = cam.intrinsics.with_focal(f[v]) if v in f else cam.intrinsics
            pred, Jp, Jf = project_with_jacobians(np.array([rows[i][2] for i in idx]), R, t, cam.cam_from_world, intr,
                                                  ("f",) if v in f else ())
            uv[idx] = pred
            J[idx, :, :6] = Jp
            if v in f:
                J[idx, :, 6 + self.free_f.index(v)] = Jf[:, :, 0]
        return uv, J

    def residuals(self, rows: list, R, t, f: dict[str, float]):
        """Weighted residuals (2n,) and their Jacobian (2n, n_par) (rotation left-increment, translation, focals)."""
        uv, J = self.project(rows, R, t, f)
        w = 1.0 / np.array([r[4] for r in rows])
        obs = np.array([r[3] for r in rows])
        return ((uv - obs) * w[:, None]).reshape(-1), (J * w[:, None, None]).reshape(-1, self.n_par)

    def refine(self, rows: list, R, t, f: dict[str, float], iterations: int = 30):
        """Gauss-Newton with Levenberg damping from ``(R, t, f)``: ``(R, t, f, residuals, Jacobian)``."""
        lam = 1e-3
        r, J = self.residuals(rows, R, t, f)
        cost = float(r @ r)
        for _ in range(iterations):
            A, g = J.T @ J, J.T @ r
            try:
                step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
            except np.linalg.LinAlgError:
                break
            R2, t2 = exp_so3(step[:3]) @ R, t + step[3:6]
            f2 = {v: max(f[v] + step[6 + i], 1.0) for i, v in enumerate(self.free_f)}
            r2, J2 = self.residuals(rows, R2, t2, f2)
            c2 = float(r2 @ r2)
            if np.isfinite(c2) and c2 < cost:
                done = cost - c2 < 1e-10 * max(cost, 1.0)
                R, t, f, r, J, cost, lam = R2, t2, f2, r2, J2, c2, max(lam / 10.0, 1e-9)
                if done:
                    break
            else:
                lam *= 10.0
                if lam > 1e8:
                    break
        return R, t, f, r, J

    def off_the_others(self, rows: list, i: int, R, t, f: dict[str, float]) -> tuple[float, float]:
        """Pick ``i`` against the pose the other picks give: (distance px, distance in sigmas: the pick's sigma
        and the prediction's, its largest axis, together)."""
        others = rows[:i] + rows[i + 1:]
        R1, t1, f1, _, J = self.refine(others, R, t, f, iterations=10)
        uv, Ji = self.project([rows[i]], R1, t1, f1)
        try:
            C = Ji[0] @ np.linalg.inv(J.T @ J) @ Ji[0].T
            var = max(float(np.linalg.eigvalsh(C)[-1]), 0.0)
        except np.linalg.LinAlgError:
            return float("nan"), 0.0
        d = float(np.hypot(*(uv[0] - rows[i][3])))
        return d, d / math.sqrt(rows[i][4] ** 2 + var)

    def screen(self, rows: list, R, t, f: dict[str, float], need: int):
        """Picks that fall far from where the others put them, one at a time (the farthest first, beyond
        :data:`FLAG_SIGMAS`), while more than ``need`` are left: ``(rows kept, [(row, distance px, sigmas)])``."""
        flagged = []
        while len(rows) > need:
            R, t, f, *_ = self.refine(rows, R, t, f)
            tests = [self.off_the_others(rows, i, R, t, f) for i in range(len(rows))]
            worst = max(range(len(rows)), key=lambda i: tests[i][1])
            if not tests[worst][1] > FLAG_SIGMAS:
                break
            flagged.append((rows[worst], *tests[worst]))
            rows = rows[:worst] + rows[worst + 1:]
        return rows, flagged


def _pnp(P: np.ndarray, uv: np.ndarray, intr, cam_from_world: np.ndarray, need: int):
    """The solver's SQPnP on all the picks, else (a wrong pick can put a point behind the camera) on all but one,
    the best of those: ``(R, t, sum of squares)`` or None."""
    hit = pnp(P, uv, intr, cam_from_world)
    if hit is not None or len(P) <= need:
        return hit
    best = None
    for i in range(len(P)):
        keep = np.arange(len(P)) != i
        h = pnp(P[keep], uv[keep], intr, cam_from_world)
        if h is not None and (best is None or h[2] < best[2]):
            best = h
    return best


def _start(car_P: dict, by_view: dict, cams: dict[str, PickerCamera], hfov_range: tuple[float, float]):
    """SQPnP in the photo with most picks that can give a pose: (view, R, t, focal or None), or a reason."""
    why = []
    for v in sorted(by_view, key=lambda v: -len(by_view[v])):
        rows = by_view[v]
        cam = cams[v]
        need = MIN_POINTS_KNOWN if cam.focal_known else MIN_POINTS_UNKNOWN
        if len(rows) < need:
            why.append(f"{v}: {len(rows)} picks, {need} needed ({'known' if cam.focal_known else 'unknown'} focal)")
            continue
        P = np.array([car_P[r[0]] for r in rows])
        uv = np.array([r[2] for r in rows])
        deg = degenerate(P, uv)
        if deg:
            why.append(f"{v}: {deg}")
            continue
        if cam.focal_known:
            hit = _pnp(P, uv, cam.intrinsics, cam.cam_from_world, need)
            if hit is not None:
                return v, hit[0], hit[1], None
            why.append(f"{v}: PnP found no pose in front of the camera")
            continue
        best = None
        for fv in focal_grid(cam.intrinsics.width, hfov_range, FOCAL_STEP_RATIO):
            hit = pnp(P, uv, cam.intrinsics.with_focal(fv), cam.cam_from_world)
            if hit is not None and (best is None or hit[2] < best[2]):
                best = (hit[0], hit[1], hit[2], float(fv))
        if best is not None:
            return v, best[0], best[1], best[3]
        why.append(f"{v}: PnP found no pose at any focal")
    return None, None, None, "; ".join(why) or "no picks in a photo with a camera"


def _predictions(ct, R, t, cov, free_f, f, cams: dict[str, PickerCamera]) -> dict:
    """Every marked point in every photo: ``{"uv", "sigma_px", "in_sight"}`` (sigma: the largest axis of its
    covariance; in_sight: the car itself does not hide it, :func:`.geometry.in_sight`)."""
    names = list(ct.marked_points)
    P = np.array([ct.marked_points[n] for n in names])
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = R, t
    out = {}
    for v, cam in cams.items():
        intr = cam.intrinsics.with_focal(f[v]) if v in f else cam.intrinsics
        M = cam.cam_from_world
        sight = dict(zip(names, in_sight(model_edges(ct), W, -M[:3, :3].T @ M[:3, 3], P, intr.fx).tolist()))
        uv = project_points(ct.marked_points, W, intr, cam.cam_from_world)
        _, Jp, Jf = project_with_jacobians(P, R, t, cam.cam_from_world, intr, ("f",) if v in free_f else ())
        pts = {}
        for i, n in enumerate(names):
            if uv[n] is None:
                continue
            Ji = np.zeros((2, cov.shape[0]))
            Ji[:, :6] = Jp[i]
            if v in free_f:
                Ji[:, 6 + free_f.index(v)] = Jf[i, :, 0]
            C = Ji @ cov @ Ji.T
            s = math.sqrt(max(float(np.linalg.eigvalsh(C)[-1]), 0.0)) if np.all(np.isfinite(C)) else None
            pts[n] = {"uv": uv[n], "sigma_px": None if s is None else round(s, 3), "in_sight": sight[n]}
        out[v] = pts
    return out


def live_pose(project: Project, payload: object, sizes: dict[str, tuple[int, int]]) -> dict:
    """The pose of one carriage from its picks (module docstring): ``{"pose": null, "reason"}`` when they do
    not fix one; else the pose, the focal per photo, each pick's residual, every marked point's predicted pixel
    with its sigma per photo, and the carriage's outline in the request's ``view``. ``sizes``: the photos a
    pick may name, with their (width, height). :class:`InputError` for a malformed request."""
    types = project.carriage_types()
    sol_focal = {}
    if project.solution_path.is_file():
        try:
            sol_focal = project.solution("picker").focal_px
        except InputError:
            sol_focal = {}
    cams = picker_cameras(project, sol_focal)
    car, obs, view = check_request(payload, {n: list(t.marked_points) for n, t in types.items()}, sizes)
    ct = types[car]
    if not cams:
        return {"carriage": car, "pose": None, "reason": "no cameras.json yet (run georef, or write one): the photos "
                                                         "have no camera to place the carriage with"}
    s = project.settings.solver
    sigma = float(s.pixel_sigma_px)
    by_view: dict[str, list] = {}
    for point, v, uv, sig in obs:
        if v in cams:
            by_view.setdefault(v, []).append((point, v, uv, max(sigma, sig or 0.0)))
    v0, R, t, f0 = _start(ct.marked_points, by_view, cams, tuple(s.hfov_range_deg))
    if v0 is None:
        return {"carriage": car, "pose": None, "reason": f0, "n_picks": len(obs)}
    # the unknown focals fitted: the start's, and any other photo with enough picks of its own
    free_f = [v for v in sorted(by_view) if not cams[v].focal_known and (v == v0 or len(by_view[v]) >= MIN_POINTS_UNKNOWN)]
    f = {v: (f0 if v == v0 and f0 is not None else cams[v].intrinsics.fx) for v in free_f}
    used = [v for v in by_view if cams[v].focal_known or v in free_f]
    rows = [(p, v, ct.marked_points[p], uv, sg) for v in used for p, _, uv, sg in by_view[v]]
    fit = _Fit(rows, cams, free_f)
    need = MIN_POINTS_UNKNOWN if free_f else MIN_POINTS_KNOWN
    kept, flagged = fit.screen(rows, R, t, f, need)
    R, t, f, r, J = fit.refine(kept, R, t, f)
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return {"carriage": car, "pose": None, "reason": "the picks do not fix the pose (singular fit)"}
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = R, t
    uv_all, _ = fit.project(rows, R, t, f)
    off = {id(row): (d, z) for row, d, z in flagged}
    picks = []
    for row, pred in zip(rows, uv_all):
        p, v, _, uv, sg = row
        e = pred - np.asarray(uv)  # not finite for a left-out pick the pose puts behind the camera: null
        fin = bool(np.all(np.isfinite(e)))
        rec = {"point": p, "view": v, "uv": list(uv),
               "residual_px": [round(float(e[0]), 3), round(float(e[1]), 3)] if fin else None,
               "distance_px": round(float(np.hypot(*e)), 3) if fin else None, "sigma_px": sg,
               "used": id(row) not in off, "flagged": id(row) in off}
        if id(row) in off:
            rec["off_the_others_px"], rec["off_the_others_sigmas"] = (round(x, 3) if math.isfinite(x) else None
                                                                      for x in off[id(row)])
        picks.append(rec)
    rr = np.array([[q["residual_px"] for q in picks if q["used"]]]).reshape(-1, 2)
    focal = {v: {"focal_px": round(float(f[v]), 3), "sigma_px": round(math.sqrt(max(cov[6 + i, 6 + i], 0.0)), 3),
                 "from": "estimated here"} for i, v in enumerate(free_f)}
    for v in used:
        focal.setdefault(v, {"focal_px": round(cams[v].intrinsics.fx, 3), "from": cams[v].focal_from})
    fcams = {v: c for v, c in cams.items() if c.focal_known or v in free_f}
    out = {"carriage": car, "pose": {"world_from_carriage": W.tolist(), "start_view": v0}, "focal": focal,
           "n_picks": len(rows), "n_used": len(kept), "dof": 2 * len(kept) - fit.n_par, "checked": len(rows) > need,
           "rms_px": round(float(np.sqrt(np.mean(np.sum(rr * rr, axis=1)))), 3),
           "picks": picks, "flagged": [p for p in picks if p["flagged"]],
           "not_used": sorted({v for _, v, _, _ in obs} - set(used)),
           "predicted": _predictions(ct, R, t, cov, free_f, f, fcams)}
    if view in fcams:
        intr = fcams[view].intrinsics.with_focal(f[view]) if view in f else fcams[view].intrinsics
        out["outline"] = outline(model_edges(ct), W, intr, fcams[view].cam_from_world)
    return out
