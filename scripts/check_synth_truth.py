"""Check a synthetic incident's ground truth against independent ray casts (trimesh, not the renderer).

    .venv/bin/python scripts/check_synth_truth.py projects/spuyten-duyvil [--out bench_out/synth_truth.json]

Prints and saves: the share of in-image marked points whose visibility flag agrees with a ray cast from the
camera against terrain, buildings and carriages, and the share of visible points that fall on their own
carriage in the instance mask.
"""
import json, sys, numpy as np, trimesh
from pathlib import Path
from PIL import Image
from workbench.project import Project
from workbench.files.dem import TerrainModel
from workbench.files.buildings import read_buildings_geojson
from workbench.terrain.extrude import building_meshes
from workbench.synth.generate import visibility_tolerance_m
from workbench.rolling_stock import get_type
from workbench.core.camera import CameraIntrinsics
root = Path(sys.argv[1]); out = Path(sys.argv[sys.argv.index("--out") + 1]) if "--out" in sys.argv else Path("bench_out/synth_truth.json"); p = Project(root); truth = json.loads((root/"truth/ground_truth.json").read_text())
tm = TerrainModel.from_geotiff(p.path(p.settings.terrain.dem), p.frame)
meshes = [tm.mesh(), *building_meshes(read_buildings_geojson(p.path(p.settings.terrain.buildings)), tm, p.frame)]
for car in truth["carriages"]:
    m = get_type(car["type"]).mesh(textured=False).copy(); m.apply_transform(np.asarray(car["world_from_carriage"])); meshes.append(m)
sm = trimesh.util.concatenate(meshes)
nv=nm=nc=na=0
for ph in truth["photos"]:
    intr = CameraIntrinsics.from_dict(ph["intrinsics"]); c = np.asarray(ph["center_enu"]); mask = np.asarray(Image.open(root/ph["mask"]))
    for car in truth["carriages"]:
        for name, o in ph["observations"][car["number"]].items():
            if not o["in_image"]: continue
            X = np.asarray(car["marked_points_enu"][name]); d = X - c; dist = np.linalg.norm(d)
            locs,_,_ = sm.ray.intersects_location([c],[d/dist]); first = np.min(np.linalg.norm(locs-c,axis=1)) if len(locs) else np.inf
            rv = first > dist - visibility_tolerance_m(dist, intr.fx)
            nc += 1; na += int(rv == o["visible"])
            if o["visible"]:
                u,v = map(int, np.round(o["uv"])); nv += 1; nm += int(car["instance_id"] in mask[max(v-2,0):v+3, max(u-2,0):u+3])
print(f"{root.name}: in-image points {nc}, visibility agrees with ray casts {na}/{nc} = {na/nc:.3f}; visible {nv}, on own mask {nm}/{nv} = {nm/nv:.3f}")
out.parent.mkdir(parents=True, exist_ok=True)
data = json.loads(out.read_text()) if out.is_file() else {}
data[root.name] = {"in_image_points": nc, "visibility_agrees": na, "visible_points": nv, "on_own_mask": nm}
out.write_text(json.dumps(data, indent=2) + "\n")
