"""The georegistration solvers' options, their residual warning, and the photos they place (docs/gis.md).

Frames and names follow docs/conventions.md: ``cam_from_rig`` (3, 3) rotations, ``cam_from_model`` (4, 4),
``p_b = b_from_a @ p_a``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, get_args

from ..core.options import Range, check_options
from ..errors import WorkbenchWarning

__all__ = ["GeorefOptions", "GeorefResidualsLarge", "HeadingPrior", "LOSSES"]

Loss = Literal["linear", "huber", "soft_l1", "cauchy"]  # scipy.optimize.least_squares' names
LOSSES = get_args(Loss)


class GeorefResidualsLarge(WorkbenchWarning):
    """Control-point residuals after georegistration are larger than expected: a point or a pick is wrong."""


@dataclass(frozen=True)
class HeadingPrior:
    """A prior on the heading of view ``view`` (its index among the views solved): the azimuth of its optical
    axis, degrees clockwise from the scene's north (+y), with a 1-sigma in degrees (EXIF ``GPSImgDirection``)."""

    view: int
    azimuth_deg: float
    sigma_deg: float
    photo: str = ""


@dataclass(frozen=True, kw_only=True)
class GeorefOptions:
    """Options of the georegistration solvers (units in the names)."""

    sigma_px: Annotated[float, Range(gt=0.0)] = 1.0  # a priori pixel noise of a pick
    loss: Loss = "soft_l1"  # robust loss of the refinement (scipy least_squares)
    loss_scale: Annotated[float, Range(gt=0.0)] = 3.0  # in units of the residuals' sigma
    # an observation is an inlier below this reprojection error
    ransac_threshold_px: Annotated[float, Range(gt=0.0)] = 12.0
    ransac_iterations: Annotated[int, Range(ge=1)] = 400
    seed: Annotated[int, Range(ge=0)] = 0  # of the random draws (RANSAC, the re-solves on perturbed data)
    prior_sigma_m: Annotated[float, Range(gt=0.0)] = 1.0  # camera.position_enu
    # multiview route (similarity, resection): EXIF GPS camera centres, east/north/up 1-sigma
    gps_sigma_m: tuple[float, float, float] = (5.0, 5.0, 10.0)
    # central routes (panorama, single; georef/priors.py, docs/gis.md "Priors from the photos' GPS and compass"):
    # the EXIF GPS centre's east and north 1-sigma is GPSHPositioningError / sqrt(2) where the photo has that
    # tag (iOS and Android write the horizontal accuracy as a radius of about 1.4-1.5 sigma), else this phone
    # default: smartphone A-GPS fixes outdoors have median horizontal errors of 5-8.5 m (Zandbergen & Barbeau
    # 2011, J. Navigation 64(3)), i.e. about 4-7 m per axis; the photo's fix may also be a few seconds stale
    gps_h_sigma_m: Annotated[float, Range(gt=0.0)] = 7.0
    # its up 1-sigma (GPSAltitude): phone altitudes are 1.5-2x worse than positions, and phones write either
    # height above sea level or above the ellipsoid (tens of metres apart); no GPSAltitude: the height is free
    gps_v_sigma_m: Annotated[float, Range(gt=0.0)] = 15.0
    # GPSImgDirection (true north) as a prior on the heading (azimuth of the optical axis): phone compasses are
    # good to 2-6 deg just after calibration and drift 2-3x without it (Lviv Polytechnic field study, 11 phones);
    # a derailment site is full of steel (rails, carriages) that bends the field: 15 deg 1-sigma
    compass_sigma_deg: Annotated[float, Range(gt=0.0)] = 15.0
    # with this many control points or fewer, the central solver starts from a grid over the centre prior and
    # widens the covariance to the scatter of ``sample_count`` re-solves on perturbed data (central.py,
    # _sample_covariance): with 2 map points the linearised covariance alone held the truth 89 % of the time
    sample_max_points: Annotated[int, Range(ge=0)] = 3
    sample_count: Annotated[int, Range(ge=0)] = 64  # 0: the linearised covariance only
    # track picks (points picked on a rail or the track centre in a photo; georef/track_picks.py): their 1-sigma
    # across the line (px; a rail is a thin line, but a hand pick on a phone photo is 1-3 px off it), the railway
    # line's horizontal 1-sigma where the layer gives no ``accuracy_m`` (OpenStreetMap tracks traced off aerial
    # imagery: about 0.5 m), and the vertical 1-sigma of the top of rail taken from the DEM (ballast and the rail
    # stand 0.2-0.5 m above the ground a DEM sees) or from the file
    track_sigma_px: Annotated[float, Range(gt=0.0)] = 2.0
    track_line_sigma_m: Annotated[float, Range(ge=0.0)] = 0.5
    track_height_sigma_m: Annotated[float, Range(ge=0.0)] = 0.3
    # a warning (GeorefResidualsLarge) when the picks' RMS residual, or one pick's residual in its photo (px) or
    # at its point (m), exceeds these
    warn_rms_px: Annotated[float, Range(gt=0.0)] = 3.0
    warn_point_px: Annotated[float, Range(gt=0.0)] = 6.0
    warn_point_m: Annotated[float, Range(gt=0.0)] = 0.5
    # multiview route: a control point is triangulated in an SfM model only where its photos' rays meet at this
    # angle or more
    min_triangulation_angle_deg: Annotated[float, Range(ge=0.0, lt=90.0)] = 2.0
    # a separate SfM model (photos SfM could not join to the main model) is placed only when its own control
    # points fix it: this many triangulated in it and fitting (all their picks inliers), spread this far from
    # the line through them (RMS, metres), an RMS pick residual within ``warn_rms_px``, at most this fraction of
    # its picks outliers, and every camera centre within this 1-sigma (from the fit's covariance, metres)
    model_min_points: Annotated[int, Range(ge=3)] = 3
    model_min_spread_m: Annotated[float, Range(gt=0.0)] = 1.0
    model_max_outlier_fraction: Annotated[float, Range(ge=0.0, lt=1.0)] = 0.25
    model_max_sigma_centre_m: Annotated[float, Range(gt=0.0)] = 0.5
    # leave out of a placed SfM model every photo whose own picks mostly disagree with it (2 or more, and more
    # than half, beyond ``ransac_threshold_px``): SfM placed it wrongly
    reject_disagreeing_views: bool = True
    # a photo in no placed model (SfM left it out, or its model could not be placed) is placed on its own from
    # its control points (resection, as the single-photo route) when ``resect_unplaced``, it has picks of this
    # many points, and the same residual and 1-sigma checks pass; intrinsics: SfM's for that photo, else the
    # main model's camera when all photos share one (``single_camera``) and the photo has its size. With 6 or
    # more fitting picks the photo's focal is refined too (fx, fy scaled together): when it differs from SfM's
    # by more than ``resect_focal_disagree_sigma`` sigma, the photo takes the refined focal (and the 1-sigma
    # check then counts the focal's uncertainty)
    resect_unplaced: bool = True
    resect_min_points: Annotated[int, Range(ge=3)] = 4
    resect_focal_disagree_sigma: Annotated[float, Range(gt=0.0)] = 2.0
    # multiview: the photos sharing one SfM camera adjusted together with its intrinsics (focal, principal point,
    # k1) from their picks; their stated uncertainty then counts the intrinsics' (docs/gis.md)
    adjust_camera: bool = True
    # its covariance is scaled by the reduced chi-square when above 1, and also when below with this many
    # degrees of freedom or more
    variance_factor_min_dof: Annotated[int, Range(ge=0)] = 50

    def __post_init__(self) -> None:
        check_options(self, "georef options")
