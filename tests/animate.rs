//! `graphs/animate.ron` end to end: the cloth never enters the ball or the floor, drapes and
//! comes to rest; `--emit` writes every frame, a GIF and an APNG of the view with the graph's
//! frame rate, and the per-frame metrics as CSV; `--frame N` runs one frame.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test code: a failed unwrap is a failed test

mod common;

use common::{ocellus, root, stderr, temp_dir};
use ocellus_engine::value::Value;

const BALL_CENTER: [f64; 3] = [0.0, 0.35, 0.0];
const BALL_RADIUS: f64 = 0.3;
const MARGIN: f64 = 0.01;
const FRAMES: usize = 48;

fn outputs() -> Vec<(String, Value)> {
    let registry = ocellus_nodes::builtin_registry().unwrap();
    ocellus_engine::testing::run_animated_graph(
        &registry,
        root().join("graphs/animate.ron"),
        0,
        &[],
    )
    .unwrap()
}

fn list<'a>(outputs: &'a [(String, Value)], name: &str) -> &'a [Value] {
    match outputs.iter().find(|(n, _)| n == name) {
        Some((_, Value::List(l))) => &l.items,
        other => panic!("{name}: {other:?}"),
    }
}

#[test]
fn the_cloth_stays_outside_the_ball_and_floor_drapes_and_settles() {
    let outputs = outputs();
    let cloth = list(&outputs, "cloth");
    assert_eq!(cloth.len(), FRAMES);
    let mut lowest_last = f64::INFINITY;
    for (f, frame) in cloth.iter().enumerate() {
        let Value::Mesh(mesh) = frame else { panic!() };
        assert_eq!(mesh.positions.len(), 24 * 24);
        for p in &mesh.positions {
            let d: f64 = (0..3)
                .map(|k| (f64::from(p[k]) - BALL_CENTER[k]).powi(2))
                .sum::<f64>()
                .sqrt();
            // f32 rounding of the emitted positions: 1e-5.
            assert!(
                d >= BALL_RADIUS + MARGIN - 1e-5,
                "frame {f}: {p:?} inside the ball"
            );
            assert!(
                f64::from(p[1]) >= MARGIN - 1e-5,
                "frame {f}: {p:?} below the floor"
            );
            if f == FRAMES - 1 {
                lowest_last = lowest_last.min(f64::from(p[1]));
            }
        }
        if f == 0 {
            assert!(mesh.positions.iter().all(|p| (p[1] - 0.9).abs() < 1e-6));
        }
    }
    // Draped: the edges hang below the ball's equator.
    assert!(lowest_last < BALL_CENTER[1], "lowest {lowest_last}");
    let Value::Metrics(physics) = &list(&outputs, "physics")[0] else {
        panic!()
    };
    let (peak, last) = (
        physics["peak_kinetic_energy_j"],
        physics["final_kinetic_energy_j"],
    );
    assert!(
        last < 0.02 * peak,
        "still moving: {last} J of a {peak} J peak"
    );
    // The camera orbits: consecutive views differ, the first and last most.
    let views = list(&outputs, "view");
    assert_eq!(views.len(), FRAMES);
    assert_ne!(views[0], views[1]);
}

#[test]
fn emit_writes_frames_gif_apng_and_csv() {
    let dir = temp_dir("animate");
    let out = ocellus(&[
        "run",
        root().join("graphs/animate.ron").to_str().unwrap(),
        "--emit",
        dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("over 48 frames at 24 fps"),
        "{}",
        stderr(&out)
    );
    for f in 0..FRAMES {
        assert!(dir.join(format!("view/{f:02}.pfm")).is_file());
        assert!(dir.join(format!("cloth/{f:02}.obj")).is_file());
        assert!(dir.join(format!("cloth/{f:02}.ply")).is_file());
        assert!(dir.join(format!("view_png/{f:02}.png")).is_file());
    }

    // GIF: 48 frames of 320×240, 4/100 s each (24 fps rounded to GIF's 10 ms), looping.
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut decoder = options
        .read_info(std::fs::File::open(dir.join("view.gif")).unwrap())
        .unwrap();
    assert_eq!((decoder.width(), decoder.height()), (320, 240));
    let mut frames = 0;
    let mut first = Vec::new();
    let mut last = Vec::new();
    while let Some(frame) = decoder.read_next_frame().unwrap() {
        assert_eq!(frame.delay, 4);
        if frames == 0 {
            first = frame.buffer.to_vec();
        }
        last = frame.buffer.to_vec();
        frames += 1;
    }
    assert_eq!(frames, FRAMES);
    assert_ne!(first, last);

    // APNG: 48 frames, 1/24 s each, pixels equal to the PNG-encoded frames' sRGB bytes.
    let decoder = png::Decoder::new(std::io::BufReader::new(
        std::fs::File::open(dir.join("view.apng")).unwrap(),
    ));
    let mut reader = decoder.read_info().unwrap();
    assert_eq!(reader.info().animation_control.unwrap().num_frames, 48);
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    reader.next_frame(&mut buf).unwrap();
    let control = reader.info().frame_control.unwrap();
    assert_eq!((control.delay_num, control.delay_den), (1, 24));
    // The APNG is lossless: frame 0 is the sRGB encoding of view/00.pfm.
    let pfm = ocellus_engine::image_io::read_image(
        &dir.join("view/00.pfm"),
        &ocellus_engine::image_io::DecodeLimits::default(),
    )
    .unwrap();
    let srgb = ocellus_engine::sequence_write::image_to_rgba8(&pfm);
    assert_eq!(buf, srgb);
    // The PNG sequence holds the same bytes, without alpha.
    let png0 = ocellus_engine::image_io::read_image(
        &dir.join("view_png/00.png"),
        &ocellus_engine::image_io::DecodeLimits::default(),
    )
    .unwrap();
    assert_eq!(ocellus_engine::sequence_write::image_to_rgba8(&png0), srgb);

    // CSV: a header and one row per frame, time = frame / fps.
    let csv = std::fs::read_to_string(dir.join("physics.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), FRAMES + 1);
    assert!(
        lines[0].starts_with("frame,time_s,colliders,"),
        "{}",
        lines[0]
    );
    for (f, line) in lines[1..].iter().enumerate() {
        let cells: Vec<&str> = line.split(',').collect();
        assert_eq!(cells[0], f.to_string());
        assert!((cells[1].parse::<f64>().unwrap() - f as f64 / 24.0).abs() < 1e-12);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn one_frame_runs_alone_and_equals_that_frame_of_the_animation() {
    let dir = temp_dir("animate-frame");
    let out = ocellus(&[
        "run",
        root().join("graphs/animate.ron").to_str().unwrap(),
        "--frame",
        "47",
        "--emit",
        dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let single = std::fs::read(dir.join("view.pfm")).unwrap();
    let all = temp_dir("animate-all");
    let out = ocellus(&[
        "run",
        root().join("graphs/animate.ron").to_str().unwrap(),
        "--output",
        "view",
        "--emit",
        all.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(single, std::fs::read(all.join("view/47.pfm")).unwrap());
    let bad = ocellus(&[
        "run",
        root().join("graphs/animate.ron").to_str().unwrap(),
        "--frame",
        "48",
    ]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(stderr(&bad).contains("the animation has frames 0 to 47"));
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::remove_dir_all(&all).unwrap();
}

#[test]
fn an_unstable_integrator_is_reported_not_rendered() {
    let out = ocellus(&[
        "run",
        root().join("graphs/animate.ron").to_str().unwrap(),
        "--set",
        "cloth.integrator=symplectic_euler",
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = stderr(&out);
    assert!(
        err.contains("symplectic_euler simulation diverged at frame"),
        "{err}"
    );
    assert!(
        err.contains("stopped at the first frame that failed"),
        "{err}"
    );
}
