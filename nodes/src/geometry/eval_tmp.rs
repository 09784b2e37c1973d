//! Throwaway evaluation dump (not committed).
use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};

use super::essential::*;
use super::pnp::*;
use super::pose_util::*;
use super::robust::Estimator;
use super::triangulate::*;

fn lcg(seed: &mut u64) -> f64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}
fn gauss(seed: &mut u64) -> f64 {
    let u1 = (lcg(seed) + 1.0) / 2.0 + 1e-300;
    let u2 = (lcg(seed) + 1.0) / 2.0;
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

#[test]
#[ignore]
fn eval_dump() {
    let k = Intrinsics::new(800.0, 800.0, 320.0, 240.0).unwrap();
    let sigma = 0.5;
    let mut out = serde_json::Map::new();
    // Relative pose trials.
    let mut rel = Vec::new();
    let mut s = 1234u64;
    for _trial in 0..100 {
        let r = *Rotation3::from_scaled_axis(Vector3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 0.2).matrix();
        let t = Vector3::new(lcg(&mut s), lcg(&mut s) * 0.3, lcg(&mut s) * 0.3).normalize();
        let mut p1 = Vec::new();
        let mut p2 = Vec::new();
        while p1.len() < 200 {
            let x = Vector3::new(lcg(&mut s) * 3.0, lcg(&mut s) * 2.0, 8.0 + 3.0 * lcg(&mut s));
            let y = r * x + t;
            let a = k.project(&x);
            let b = k.project(&y);
            if y.z > 0.0 && a[0] > 0.0 && a[0] < 640.0 && a[1] > 0.0 && a[1] < 480.0 && b[0] > 0.0 && b[0] < 640.0 && b[1] > 0.0 && b[1] < 480.0 {
                p1.push([a[0] + sigma * gauss(&mut s), a[1] + sigma * gauss(&mut s)]);
                p2.push([b[0] + sigma * gauss(&mut s), b[1] + sigma * gauss(&mut s)]);
            }
        }
        let data: Vec<NormalizedPair> = p1.iter().zip(&p2).map(|(a, b)| (k.normalize(*a).into(), k.normalize(*b).into())).collect();
        let est = EssentialEstimator { focal_px: k.focal() };
        // Minimal MSAC loop, 200 iterations, threshold 1 px.
        let thr = 1.0;
        let mut best = (f64::INFINITY, Matrix3::zeros());
        let mut res = vec![0.0; data.len()];
        let mut ss = 99u64;
        for _ in 0..200 {
            let mut idx = [0usize; 5];
            let mut c = 0;
            while c < 5 {
                let i = (((lcg(&mut ss) + 1.0) / 2.0) * data.len() as f64) as usize % data.len();
                if !idx[..c].contains(&i) { idx[c] = i; c += 1; }
            }
            let sample: Vec<NormalizedPair> = idx.iter().map(|&i| data[i]).collect();
            for m in est.fit(&sample) {
                est.residuals(&m, &data, &mut res);
                let cost: f64 = res.iter().map(|&r| r.min(thr * thr)).sum();
                if cost < best.0 { best = (cost, m); }
            }
        }
        est.residuals(&best.1, &data, &mut res);
        let inl: Vec<NormalizedPair> = data.iter().zip(&res).filter(|(_, r)| **r < thr * thr).map(|(d, _)| *d).collect();
        let e_ref = est.fit_nonminimal(&inl).into_iter().next().unwrap_or(best.1);
        let x1: Vec<[f64; 2]> = data.iter().map(|d| d.0).collect();
        let x2: Vec<[f64; 2]> = data.iter().map(|d| d.1).collect();
        let pose5 = decompose_essential(&best.1, &x1, &x2, 0.0).unwrap();
        let pose8 = decompose_essential(&e_ref, &x1, &x2, 0.0).unwrap();
        let x1v: Vec<Vector2<f64>> = x1.iter().map(|p| Vector2::from(*p)).collect();
        let x2v: Vec<Vector2<f64>> = x2.iter().map(|p| Vector2::from(*p)).collect();
        let e8all = essential_eight_point(&x1v, &x2v).unwrap();
        let pose8all = decompose_essential(&e8all, &x1, &x2, 0.0).unwrap();
        rel.push(serde_json::json!({
            "r": r.transpose().as_slice(), "t": t.as_slice(), "p1": p1, "p2": p2,
            "ours5": [rotation_angle_deg(&pose5.r, &r), vector_angle_deg(&pose5.t, &t)],
            "ours5_refit": [rotation_angle_deg(&pose8.r, &r), vector_angle_deg(&pose8.t, &t)],
            "ours8_all": [rotation_angle_deg(&pose8all.r, &r), vector_angle_deg(&pose8all.t, &t)],
        }));
    }
    out.insert("relative".into(), serde_json::Value::Array(rel));
    // PnP trials.
    let mut pnp = Vec::new();
    for _trial in 0..100 {
        let r = *Rotation3::from_scaled_axis(Vector3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 1.5).matrix();
        let t = Vector3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s));
        let mut px = Vec::new();
        let mut w = Vec::new();
        for _ in 0..100 {
            let c = Vector3::new(lcg(&mut s) * 2.0, lcg(&mut s) * 1.5, 6.0 + 2.0 * lcg(&mut s));
            let x = r.transpose() * (c - t);
            let q = k.project(&c);
            px.push([q[0] + sigma * gauss(&mut s), q[1] + sigma * gauss(&mut s)]);
            w.push([x.x, x.y, x.z]);
        }
        let err = |p: &CameraPose| [rotation_angle_deg(&p.r, &r), (p.t - t).norm() / t.norm().max(1e-9), vector_angle_deg(&p.t, &t)];
        let e = epnp(&k, &px, &w).unwrap();
        let el = refine_pose(&k, &px, &w, &e, 50);
        let p3 = p3p_best(&k, &px[..4], &w[..4], [0, 1, 2]).unwrap();
        let d = pnp_dlt(&k, &px, &w).unwrap();
        pnp.push(serde_json::json!({
            "r": r.transpose().as_slice(), "t": t.as_slice(), "px": px, "w": w,
            "epnp": err(&e), "epnp_lm": err(&el), "p3p4": err(&p3), "dlt": err(&d),
        }));
    }
    out.insert("pnp".into(), serde_json::Value::Array(pnp));
    // Triangulation: 1000 points.
    let r = *Rotation3::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)).matrix();
    let t = Vector3::new(-1.0, 0.1, 0.2);
    let v1 = View { r: Matrix3::identity(), t: Vector3::zeros(), k };
    let v2 = View { r, t, k };
    let mut pts = Vec::new();
    let mut p1 = Vec::new();
    let mut p2 = Vec::new();
    for _ in 0..1000 {
        let x = Vector3::new(2.0 * lcg(&mut s), 1.5 * lcg(&mut s), 6.0 + 2.0 * lcg(&mut s));
        let a = k.project(&x);
        let b = k.project(&(r * x + t));
        pts.push([x.x, x.y, x.z]);
        p1.push([a[0] + sigma * gauss(&mut s), a[1] + sigma * gauss(&mut s)]);
        p2.push([b[0] + sigma * gauss(&mut s), b[1] + sigma * gauss(&mut s)]);
    }
    let mut tri = serde_json::Map::new();
    for (name, m) in [("dlt", TriangulationMethod::Dlt), ("midpoint", TriangulationMethod::Midpoint), ("optimal", TriangulationMethod::Optimal)] {
        let res = triangulate_points(&v1, &v2, &p1, &p2, m, 0.5).unwrap();
        let errs: Vec<f64> = res.iter().zip(&pts).map(|(t, x)| (t.point.unwrap() - Vector3::from(*x)).norm()).collect();
        let reproj: f64 = res.iter().zip(p1.iter().zip(&p2)).map(|(tr, (a, b))| {
            let q = tr.point.unwrap();
            let u = k.project(&q);
            let v = k.project(&(r * q + t));
            (u[0]-a[0]).powi(2)+(u[1]-a[1]).powi(2)+(v[0]-b[0]).powi(2)+(v[1]-b[1]).powi(2)
        }).sum::<f64>() / 1000.0;
        tri.insert(name.into(), serde_json::json!({"mean_err": errs.iter().sum::<f64>() / 1000.0, "mean_sq_reproj": reproj,
            "mean_depth_std": res.iter().map(|t| t.depth_std).sum::<f64>() / 1000.0}));
    }
    tri.insert("r".into(), serde_json::json!(r.transpose().as_slice()));
    tri.insert("pts".into(), serde_json::json!(pts));
    tri.insert("p1".into(), serde_json::json!(p1));
    tri.insert("p2".into(), serde_json::json!(p2));
    out.insert("tri".into(), serde_json::Value::Object(tri));
    std::fs::write("/tmp/h26_eval.json", serde_json::to_string(&out).unwrap()).unwrap();
}

