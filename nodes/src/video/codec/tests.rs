use super::stream::*;
use super::*;
use crate::video::synth::blob_texture;

/// `frames` frames of a blob texture translating by (sx, sy) px per frame:
/// frame t+1 at (x, y) = frame t at (x − sx, y − sy).
fn translating(w: usize, h: usize, frames: usize, sx: i32, sy: i32, seed: u64) -> Vec<LumaFrame> {
    (0..frames)
        .map(|t| {
            let map = [
                1.0,
                0.0,
                -(t as f64) * f64::from(sx),
                0.0,
                1.0,
                -(t as f64) * f64::from(sy),
            ];
            let image = blob_texture(w, h, 3.0, seed, map).unwrap();
            let data = image
                .as_f32()
                .unwrap()
                .iter()
                .map(|&v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                .collect();
            LumaFrame {
                width: w,
                height: h,
                data,
            }
        })
        .collect()
}

fn config(quantizer: f64, gop: usize) -> CodecConfig {
    CodecConfig {
        quantizer,
        flat: false,
        gop,
        search_px: 8,
        method: SearchMethod::Full,
    }
}

fn mean_psnr(e: &Encoded) -> f64 {
    e.stats.iter().map(|s| s.psnr_db).sum::<f64>() / e.stats.len() as f64
}

#[test]
fn decoder_output_equals_the_encoder_reconstruction_bit_exactly() {
    // 40×24 is not a multiple of 16: padded to 48×32 and cropped back.
    let frames = translating(40, 24, 6, 2, 1, 3);
    for flat in [false, true] {
        let cfg = CodecConfig {
            flat,
            ..config(6.0, 4)
        };
        let encoded = encode(&frames, &cfg).unwrap();
        let decoded = decode(&encoded.bytes).unwrap();
        assert_eq!(decoded.frames, encoded.frames);
        assert_eq!(decoded.frames[0].width, 40);
        assert_eq!(decoded.frames[0].height, 24);
        assert_eq!(decoded.flat, flat);
        let kinds: Vec<_> = encoded.stats.iter().map(|s| (s.kind, s.bits)).collect();
        assert_eq!(decoded.kinds, kinds);
        assert_eq!(
            kinds.iter().map(|k| k.0).collect::<Vec<_>>(),
            [
                FrameKind::I,
                FrameKind::P,
                FrameKind::P,
                FrameKind::P,
                FrameKind::I,
                FrameKind::P
            ]
        );
        // The stream is exactly header + frame bits, padded to a byte.
        let bits: u64 = kinds.iter().map(|k| k.1).sum();
        assert_eq!(encoded.bytes.len() as u64, (HEADER_BITS + bits).div_ceil(8));
    }
}

#[test]
fn finest_quantizer_gives_high_psnr_and_more_bits() {
    let frames = translating(48, 48, 3, 1, 1, 5);
    let fine = encode(&frames, &config(0.25, 3)).unwrap();
    let coarse = encode(&frames, &config(16.0, 3)).unwrap();
    for s in &fine.stats {
        assert!(s.psnr_db > 45.0, "PSNR {} dB at quantizer 0.25", s.psnr_db);
    }
    assert!(fine.bytes.len() > 2 * coarse.bytes.len());
    assert!(mean_psnr(&fine) > mean_psnr(&coarse) + 10.0);
}

#[test]
fn psnr_and_bits_fall_as_the_quantizer_grows() {
    let frames = translating(48, 32, 4, 2, 0, 9);
    let runs: Vec<Encoded> = [1.0, 4.0, 16.0, 48.0]
        .iter()
        .map(|&q| encode(&frames, &config(q, 2)).unwrap())
        .collect();
    for pair in runs.windows(2) {
        assert!(
            mean_psnr(&pair[0]) > mean_psnr(&pair[1]),
            "{} vs {}",
            mean_psnr(&pair[0]),
            mean_psnr(&pair[1])
        );
        assert!(pair[0].bytes.len() > pair[1].bytes.len());
    }
}

#[test]
fn p_frames_of_a_translation_cost_far_fewer_bits_than_i_frames() {
    let frames = translating(128, 96, 3, 2, 1, 11);
    let inter = encode(&frames, &config(8.0, 3)).unwrap();
    let intra = encode(&frames, &config(8.0, 1)).unwrap();
    let p_bits: u64 = inter.stats[1..].iter().map(|s| s.bits).sum();
    let i_bits: u64 = intra.stats[1..].iter().map(|s| s.bits).sum();
    assert!(
        (p_bits as f64) < 0.5 * i_bits as f64,
        "P {p_bits} bits vs I {i_bits} bits"
    );
    // At about equal quality (same quantizer).
    let (pp, pi) = (mean_psnr(&inter), mean_psnr(&intra));
    assert!((pp - pi).abs() < 1.5, "PSNR P {pp} dB vs I {pi} dB");
}

#[test]
fn motion_vectors_recover_a_global_translation() {
    let (sx, sy) = (3, -2);
    let (w, h) = (96, 80);
    let frames = translating(w, h, 3, sx, sy, 21);
    for method in [SearchMethod::Full, SearchMethod::CoarseToFine] {
        let cfg = CodecConfig {
            method,
            ..config(2.0, 3)
        };
        let encoded = encode(&frames, &cfg).unwrap();
        for s in &encoded.stats[1..] {
            let cols = w.div_ceil(MB);
            let mut interior = 0;
            for (i, &mv) in s.vectors.iter().enumerate() {
                let (x0, y0) = ((i % cols * MB) as i32, (i / cols * MB) as i32);
                // The true match lies inside the frame (and away from the padding).
                let inside = x0 - sx >= 0
                    && y0 - sy >= 0
                    && x0 - sx + MB as i32 <= w as i32
                    && y0 - sy + MB as i32 <= h as i32;
                if inside {
                    interior += 1;
                    if method == SearchMethod::Full {
                        assert_eq!(mv, (-sx, -sy), "macroblock {i}");
                    }
                }
            }
            assert!(interior >= 12);
            let hits = s.vectors.iter().filter(|&&v| v == (-sx, -sy)).count();
            assert!(hits >= interior * 3 / 4, "{method:?}: {hits} of {interior}");
        }
    }
}

#[test]
fn truncated_or_corrupt_streams_are_errors_not_panics() {
    let frames = translating(24, 16, 3, 1, 0, 2);
    let bytes = encode(&frames, &config(8.0, 2)).unwrap().bytes;
    for k in 0..bytes.len() {
        let err = decode(&bytes[..k]).unwrap_err();
        assert!(
            err.contains("truncated") || err.contains("header") || err.contains("corrupt"),
            "{k}: {err}"
        );
    }
    let mut extra = bytes.clone();
    extra.push(0);
    assert!(decode(&extra).unwrap_err().contains("follow"));
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(decode(&bad).unwrap_err().contains("OCVC"));
    // Any single flipped bit: an error or some frames, never a panic.
    for i in 0..bytes.len() * 8 {
        let mut flipped = bytes.clone();
        flipped[i / 8] ^= 0x80 >> (i % 8);
        let _ = decode(&flipped);
    }
}

#[test]
fn frames_of_different_sizes_are_an_error() {
    let mut frames = translating(32, 32, 2, 0, 0, 1);
    frames.push(translating(16, 32, 1, 0, 0, 1).remove(0));
    let err = encode(&frames, &config(8.0, 4)).unwrap_err();
    assert!(err.contains("frame 2"), "{err}");
    assert!(encode(&[], &config(8.0, 4)).is_err());
    assert!(encode(&frames[..1], &config(f64::NAN, 4)).is_err());
    assert!(encode(&frames[..1], &config(8.0, 0)).is_err());
}

#[test]
fn odd_sizes_round_trip_through_padding() {
    for (w, h) in [(1, 1), (17, 9), (33, 50)] {
        let frames = translating(w, h, 2, 1, 1, 4);
        let encoded = encode(&frames, &config(0.5, 2)).unwrap();
        let decoded = decode(&encoded.bytes).unwrap();
        assert_eq!(decoded.frames, encoded.frames);
        for (a, b) in decoded.frames.iter().zip(&frames) {
            assert_eq!((a.width, a.height), (w, h));
            let err = a
                .data
                .iter()
                .zip(&b.data)
                .map(|(&x, &y)| x.abs_diff(y))
                .max()
                .unwrap();
            assert!(err <= 2, "{w}×{h}: max error {err}");
        }
    }
}

#[test]
fn the_bitstream_is_the_same_for_any_thread_count() {
    let frames = translating(64, 48, 4, 2, 1, 8);
    let run = |threads| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| encode(&frames, &config(6.0, 3)).unwrap())
    };
    assert_eq!(run(1), run(3));
}

#[test]
fn operators_round_trip_through_a_byte_matrix_and_a_file() {
    let images: Vec<Value> = translating(32, 24, 3, 1, 0, 6)
        .into_iter()
        .map(|f| Value::image(Image::from_u8(32, 24, Channels::Gray, f.data).unwrap()))
        .collect();
    let ctx = RunContext {
        node: "n".into(),
        threads: 1,
        element: None,
    };
    let enc = Encode::new(EncodeParams {
        gop: 2,
        ..EncodeParams::default()
    })
    .unwrap();
    let specs = Encode::inputs();
    let values = [Some(Value::list(PortType::Image, images))];
    let mut out = enc.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
    let bitstream = out.take("bitstream").unwrap();
    let recon = out.take("frames").unwrap();
    let Some(Value::Matrix(per_frame)) = out.take("per_frame") else {
        panic!()
    };
    assert_eq!((per_frame.rows, per_frame.cols), (3, 6));
    assert_eq!(per_frame.get(1, 1), Some(1.0));

    let dir = std::env::temp_dir().join(format!("ocellus-codec-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("clip.ocv");
    let write = WriteBitstream::new(WriteBitstreamParams { path: path.clone() }).unwrap();
    let wspecs = WriteBitstream::inputs();
    let wvalues = [Some(bitstream.clone())];
    write.run(&ctx, &Inputs::new(&wspecs, &wvalues)).unwrap();
    let read = ReadBitstream::new(ReadBitstreamParams { path }).unwrap();
    let mut loaded = read.run(&ctx, &Inputs::new(&[], &[])).unwrap();
    assert_eq!(loaded.take("bitstream").unwrap(), bitstream);
    std::fs::remove_dir_all(&dir).unwrap();

    let dspecs = Decode::inputs();
    let dvalues = [Some(bitstream)];
    let mut dec = Decode.run(&ctx, &Inputs::new(&dspecs, &dvalues)).unwrap();
    assert_eq!(dec.take("frames").unwrap(), recon);

    // Not bytes: rejected with the port named.
    let bad = Value::Matrix(Arc::new(Matrix::new(2, 1, vec![79.0, 256.0]).unwrap()));
    let bvalues = [Some(bad)];
    let err = Decode
        .run(&ctx, &Inputs::new(&dspecs, &bvalues))
        .unwrap_err();
    assert!(err.to_string().contains("bitstream"), "{err}");
    assert!(
        Encode::new(EncodeParams {
            gop: 0,
            ..EncodeParams::default()
        })
        .is_err()
    );
}
