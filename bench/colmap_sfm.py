"""COLMAP (pycolmap) incremental SfM on a folder of images, scored against Middlebury-style
true cameras (`NAME_par.txt`: per line `name k11..k33 r11..r33 t1 t2 t3`, x ~ K[R|t]X) with
the same similarity alignment and error measures as `analyze.reconstruction_error`.

    python bench/colmap_sfm.py IMAGES_DIR PAR_FILE [--focal 1520] [--threads 2]

Prints one JSON line: registered images, points, reprojection RMS, rotation and camera-centre
errors (median / max; centre errors as a share of the true cameras' extent, the same "scene
size" Ocellus uses: the diagonal of the bounding box of all true camera centres) and wall times.
"""

import argparse
import json
import os
import shutil
import tempfile
import time

import numpy as np
import pycolmap


def read_par(path):
    cams = {}
    with open(path) as f:
        n = int(f.readline())
        for _ in range(n):
            v = f.readline().split()
            name, x = v[0], np.array([float(t) for t in v[1:]])
            cams[name] = (x[0:9].reshape(3, 3), x[9:18].reshape(3, 3), x[18:21])
    return cams


def umeyama(src, dst):
    """s, R, t minimising |dst - (s R src + t)|² (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    s_fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[2, 2] = -1
    r = u @ s_fix @ vt
    var = (a**2).sum() / len(src)
    s = np.trace(np.diag(d) @ s_fix) / var
    return s, r, mu_d - s * r @ mu_s


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("images")
    ap.add_argument("par")
    ap.add_argument("--focal", type=float, default=0.0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    truth = read_par(args.par)
    work = tempfile.mkdtemp()
    db = os.path.join(work, "db.db")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    names = sorted(n for n in os.listdir(args.images) if n.lower().endswith((".png", ".jpg")))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = args.threads
    t0 = time.perf_counter()
    if args.focal > 0:
        # The principal point at the image centre, as COLMAP initialises it.
        first = pycolmap.Bitmap.read(os.path.join(args.images, names[0]), False)
        w, h = first.width, first.height
        reader.camera_params = f"{args.focal},{w / 2},{h / 2},0"
    pycolmap.extract_features(db, args.images, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction,
                              device=pycolmap.Device.cpu)
    t1 = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = args.threads
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    t2 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = args.threads
    maps = pycolmap.incremental_mapping(db, args.images, os.path.join(work, "sparse"), options=opts)
    t3 = time.perf_counter()
    best = max(maps.values(), key=lambda r: r.num_reg_images()) if maps else None
    out = {"images": len(names), "models": len(maps),
           "time_features_s": t1 - t0, "time_matching_s": t2 - t1, "time_mapping_s": t3 - t2,
           "time_total_s": t3 - t0}
    if best is not None:
        est_c, true_c, rot_pairs = [], [], []
        for img in best.images.values():
            if not img.has_pose or img.name not in truth:
                continue
            cfw = img.cam_from_world()
            r_est = cfw.rotation.matrix()
            t_est = cfw.translation
            k, r_true, t_true = truth[img.name]
            est_c.append(-r_est.T @ t_est)
            true_c.append(-r_true.T @ t_true)
            rot_pairs.append((r_est, r_true))
        est_c, true_c = np.array(est_c), np.array(true_c)
        s, r_align, _ = umeyama(est_c, true_c)
        aligned = (s * (r_align @ est_c.T)).T + (true_c.mean(0) - s * r_align @ est_c.mean(0))
        every = np.array([-r.T @ t for _, r, t in truth.values()])
        size = np.linalg.norm(every.max(0) - every.min(0))
        centre = np.linalg.norm(aligned - true_c, axis=1) / size
        rot = []
        for r_est, r_true in rot_pairs:
            # world_true = s R_align world_est + t: R_cam_true ≈ R_est R_alignᵀ.
            d = r_true @ (r_est @ r_align.T).T
            rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
        cam = next(iter(best.cameras.values()))
        out.update({
            "registered": best.num_reg_images(), "points": best.num_points3D(),
            "reprojection_rms_px": float(np.sqrt(np.mean([p.error**2 for p in best.points3D.values()]))),
            "focal_px": float(cam.params[0]),
            "rotation_error_median_deg": float(np.median(rot)), "rotation_error_max_deg": float(np.max(rot)),
            "centre_error_median": float(np.median(centre)), "centre_error_max": float(np.max(centre)),
        })
    shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
