//! Every format decoded against known pixels; packed bytes written out by hand from the
//! PFNC and GigE Vision layouts.

use super::*;

fn unit() -> BayerBalance {
    BayerBalance::fixed([1.0, 1.0, 1.0])
}

#[test]
fn mono_8_and_16_bit_words_with_row_padding() {
    let f8 = SampleFormat::mono(Packing::U8, 8);
    let data = [1, 2, 3, 99, 4, 5, 6, 99];
    let got = to_grey(&f8, &data, 3, 2, 4, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray8(vec![1, 2, 3, 4, 5, 6]));
    let f12 = SampleFormat::mono(Packing::U16Le, 12);
    let data = [0xBC, 0x0A, 0x23, 0x01];
    let got = to_grey(&f12, &data, 2, 1, 4, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0xABC, 0x123]));
}

#[test]
fn pfnc_bit_streams_unpack_lsb_first() {
    // Mono10p: four pixels in five bytes.
    let f = SampleFormat::mono(Packing::LsbStream, 10);
    let data = [0xFF, 0x07, 0x50, 0x95, 0xAA];
    assert_eq!(f.row_bytes(4), Some(5));
    let got = to_grey(&f, &data, 4, 1, 5, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0x3FF, 0x001, 0x155, 0x2AA]));
    // Mono12p: two pixels in three bytes, two rows.
    let f = SampleFormat::mono(Packing::LsbStream, 12);
    let data = [0xBC, 0x3A, 0x12, 0xBC, 0x3A, 0x12];
    let got = to_grey(&f, &data, 2, 2, 3, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0xABC, 0x123, 0xABC, 0x123]));
}

#[test]
fn gige_vision_packed_pairs_unpack() {
    let f = SampleFormat::mono(Packing::GvspPair, 12);
    let got = to_grey(&f, &[0xAB, 0x3C, 0x12], 2, 1, 3, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0xABC, 0x123]));
    let f = SampleFormat::mono(Packing::GvspPair, 10);
    let got = to_grey(&f, &[0xAD, 0x13, 0x72], 2, 1, 3, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0x2B7, 0x1C9]));
    // A pair cannot hold an odd width.
    assert!(matches!(
        unpack(&f, &[0; 6], 3, 1, 6),
        Err(FormatError::Layout(_))
    ));
}

#[test]
fn short_buffers_are_refused_not_read_past() {
    let f = SampleFormat::mono(Packing::U16Le, 16);
    let e = to_grey(&f, &[0; 7], 2, 2, 4, &mut unit()).unwrap_err();
    assert_eq!(
        e,
        FormatError::Short {
            got: 7,
            need: 8,
            width: 2,
            height: 2
        }
    );
}

#[test]
fn cfa_phases_name_the_top_left_cell() {
    let colours = |cfa: Cfa| {
        [(0, 0), (1, 0), (0, 1), (1, 1)].map(|(x, y)| ["R", "G", "B"][cfa.channel(x, y)])
    };
    assert_eq!(colours(Cfa::Rggb), ["R", "G", "G", "B"]);
    assert_eq!(colours(Cfa::Grbg), ["G", "R", "B", "G"]);
    assert_eq!(colours(Cfa::Gbrg), ["G", "B", "R", "G"]);
    assert_eq!(colours(Cfa::Bggr), ["B", "G", "G", "R"]);
    // The pattern repeats every two pixels.
    for cfa in Cfa::ALL {
        assert_eq!(cfa.channel(0, 0), cfa.channel(2, 4));
        assert_eq!(cfa.channel(1, 1), cfa.channel(5, 3));
    }
}

/// A neutral 4×4 scene of `level` seen through `cfa` with responses `response`, as
/// `format` bytes.
fn mosaic(cfa: Cfa, response: [f64; 3], level: f64) -> Vec<u16> {
    (0..16)
        .map(|i| (level * response[cfa.channel(i % 4, i / 4)]).round() as u16)
        .collect()
}

#[test]
fn bayer_mosaics_of_every_phase_and_depth_balance_to_one_grey() {
    let response = [0.5, 1.0, 0.8];
    for cfa in Cfa::ALL {
        // 8 bits, one byte each.
        let raw = mosaic(cfa, response, 200.0);
        let bytes: Vec<u8> = raw.iter().map(|&v| v as u8).collect();
        let f = SampleFormat::bayer(cfa, Packing::U8, 8);
        let mut balance = BayerBalance::default();
        let got = to_grey(&f, &bytes, 4, 4, 4, &mut balance).unwrap();
        assert_eq!(got, Pixels::Gray8(vec![200; 16]), "{cfa:?}");
        let g = balance.gains().unwrap();
        assert!(
            (g[0] - 2.0).abs() < 1e-12 && (g[2] - 1.25).abs() < 1e-12,
            "{g:?}"
        );
        // 10, 12 and 16 bits in 16-bit words.
        for bits in [10u8, 12, 16] {
            let level = f64::from((1u32 << bits) - 1) * 0.75;
            let raw = mosaic(cfa, response, level);
            let bytes: Vec<u8> = raw.iter().flat_map(|v| v.to_le_bytes()).collect();
            let f = SampleFormat::bayer(cfa, Packing::U16Le, bits);
            let got = to_grey(&f, &bytes, 4, 4, 8, &mut BayerBalance::default()).unwrap();
            let Pixels::Gray16(got) = got else {
                panic!("16-bit samples expected")
            };
            // Rounding the mosaic to integers costs at most a gain's worth of a half DN.
            assert!(
                got.iter()
                    .all(|&v| (f64::from(v) - level.round()).abs() <= 1.0),
                "{cfa:?} {bits}: {got:?}"
            );
        }
    }
}

#[test]
fn packed_bayer_unpacks_then_balances() {
    // BayerRG12p: R=0x400, G=0x800 | G=0x800, B=0x200 with gains (2, 1, 4) → all 0x800.
    let f = SampleFormat::bayer(Cfa::Rggb, Packing::LsbStream, 12);
    let data = [0x00, 0x04, 0x80, 0x00, 0x08, 0x20];
    let mut balance = BayerBalance::fixed([2.0, 1.0, 4.0]);
    let got = to_grey(&f, &data, 2, 2, 3, &mut balance).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0x800; 4]));
    // BayerGB10Packed.
    let f = SampleFormat::bayer(Cfa::Gbrg, Packing::GvspPair, 10);
    let got = to_grey(&f, &[0xAD, 0x13, 0x72], 2, 1, 3, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray16(vec![0x2B7, 0x1C9]));
}

#[test]
fn balance_is_measured_once_and_waits_for_a_bright_frame() {
    let f = SampleFormat::bayer(Cfa::Bggr, Packing::U8, 8);
    let response = [0.6, 1.0, 0.9];
    let mut balance = BayerBalance::default();
    // A dark frame (green mean below 255/16) leaves the gains unmeasured, the frame as is.
    let dark: Vec<u8> = mosaic(Cfa::Bggr, response, 10.0)
        .iter()
        .map(|&v| v as u8)
        .collect();
    let got = to_grey(&f, &dark, 4, 4, 4, &mut balance).unwrap();
    assert_eq!(balance.gains(), None);
    assert_eq!(
        got,
        to_pixels(dark.iter().map(|&v| u16::from(v)).collect(), 8)
    );
    let bright: Vec<u8> = mosaic(Cfa::Bggr, response, 150.0)
        .iter()
        .map(|&v| v as u8)
        .collect();
    to_grey(&f, &bright, 4, 4, 4, &mut balance).unwrap();
    let held = balance.gains().unwrap();
    // A later frame of other colours does not change the gains held.
    to_grey(&f, &[255; 16], 4, 4, 4, &mut balance).unwrap();
    assert_eq!(balance.gains(), Some(held));
    assert!((held[0] - 150.0 / 90.0).abs() < 1e-12, "{held:?}");
}

#[test]
fn rgb_and_bgr_give_bt601_luma_and_yuyv_its_luma() {
    let rgb = [200, 100, 50, 0, 0, 0];
    let f = SampleFormat::bytes(Colour::Rgb);
    let got = to_grey(&f, &rgb, 2, 1, 6, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray8(vec![124, 0]));
    let bgr = [50, 100, 200, 255, 255, 255];
    let f = SampleFormat::bytes(Colour::Bgr);
    let got = to_grey(&f, &bgr, 2, 1, 6, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray8(vec![124, 255]));
    let yuyv = [10, 128, 20, 128, 30, 0, 40, 255];
    let f = SampleFormat::bytes(Colour::YuyvLuma);
    let got = to_grey(&f, &yuyv, 2, 2, 4, &mut unit()).unwrap();
    assert_eq!(got, Pixels::Gray8(vec![10, 20, 30, 40]));
}

/// A JPEG of `raw` pixels (`colour` L8 or Rgb8) at `quality`.
fn encode(raw: &[u8], w: u32, h: u32, colour: image::ExtendedColorType, quality: u8) -> Vec<u8> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality)
        .encode(raw, w, h, colour)
        .unwrap();
    out
}

#[test]
fn jpeg_gives_its_luma_plane() {
    // A smooth grey ramp survives quality 100 to within 1 DN.
    let (w, h) = (32u32, 16u32);
    let grey = image::GrayImage::from_fn(w, h, |x, y| image::Luma([(40 + 5 * x + 2 * y) as u8]));
    let data = encode(grey.as_raw(), w, h, image::ExtendedColorType::L8, 100);
    let f = SampleFormat::bytes(Colour::Jpeg);
    let Pixels::Gray8(got) = to_grey(&f, &data, 32, 16, 0, &mut unit()).unwrap() else {
        panic!("8-bit luma expected")
    };
    let worst = got
        .iter()
        .zip(grey.as_raw())
        .map(|(&a, &b)| (i16::from(a) - i16::from(b)).abs())
        .max();
    assert!(worst <= Some(1), "worst {worst:?}");
    // A colour JPEG (YCbCr) gives the BT.601 luma of its pixels, not a mix of its chroma.
    let rgb = image::RgbImage::from_fn(w, h, |x, _| match x < 16 {
        true => image::Rgb([200, 100, 50]),
        false => image::Rgb([20, 60, 220]),
    });
    let data = encode(rgb.as_raw(), w, h, image::ExtendedColorType::Rgb8, 100);
    let Pixels::Gray8(got) = to_grey(&f, &data, 32, 16, 0, &mut unit()).unwrap() else {
        panic!("8-bit luma expected")
    };
    // BT.601: 0.299·R + 0.587·G + 0.114·B = 124.2 and 66.3.
    let want = |x: usize| if x < 16 { 124 } else { 66 };
    for (i, &v) in got.iter().enumerate() {
        // Away from the colour edge (JPEG rings across it).
        if !(12..20).contains(&(i % 32)) {
            assert!((i16::from(v) - want(i % 32)).abs() <= 2, "pixel {i}: {v}");
        }
    }
}

#[test]
fn jpeg_of_another_size_or_garbage_is_an_error() {
    let grey = image::GrayImage::from_pixel(16, 8, image::Luma([90]));
    let data = encode(grey.as_raw(), 16, 8, image::ExtendedColorType::L8, 90);
    let f = SampleFormat::bytes(Colour::Jpeg);
    let e = to_grey(&f, &data, 32, 8, 0, &mut unit()).unwrap_err();
    assert!(
        matches!(e, FormatError::JpegSize { .. } | FormatError::Jpeg(_)),
        "{e}"
    );
    // A frame cut short in transfer is refused; zero padding after the end is not.
    let e = to_grey(&f, &data[..data.len() / 3], 16, 8, 0, &mut unit()).unwrap_err();
    assert!(matches!(e, FormatError::Jpeg(_)), "{e}");
    let mut padded = data.clone();
    padded.extend([0; 100]);
    assert!(to_grey(&f, &padded, 16, 8, 0, &mut unit()).is_ok());
    let e = to_grey(&f, b"not a jpeg at all", 16, 8, 0, &mut unit()).unwrap_err();
    assert!(matches!(e, FormatError::Jpeg(_)), "{e}");
}

#[test]
fn preference_puts_mono_first_and_mjpeg_last() {
    let mono = SampleFormat::mono(Packing::U8, 8);
    let bayer = SampleFormat::bayer(Cfa::Rggb, Packing::U8, 8);
    let rgb = SampleFormat::bytes(Colour::Rgb);
    let jpeg = SampleFormat::bytes(Colour::Jpeg);
    let ranks: Vec<_> = [jpeg, rgb, bayer, mono]
        .iter()
        .map(|f| f.rank(8).unwrap())
        .collect();
    assert!(ranks.windows(2).all(|w| w[0] > w[1]), "{ranks:?}");
    // 12 bits: exactly 12 before a 16-bit container; 8 bits cannot serve 12.
    let m12 = SampleFormat::mono(Packing::LsbStream, 12);
    let m16 = SampleFormat::mono(Packing::U16Le, 16);
    assert!(m12.rank(12).unwrap() < m16.rank(12).unwrap());
    assert_eq!(mono.rank(12), None);
    assert_eq!(jpeg.rank(12), None);
}

#[test]
fn gains_come_from_the_bright_cells_and_ignore_a_dark_backgrounds_offset() {
    // A 64×64 neutral scene: a bright square (160 DN at green) over a tenth of the frame,
    // the rest black with a 2 DN offset on every channel (a black level, or read noise
    // clipped at zero). Filters respond 0.6, 1, 0.8.
    let response = [0.6, 1.0, 0.8];
    let (w, h) = (64usize, 64usize);
    for cfa in Cfa::ALL {
        let raw: Vec<u16> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let bright = x < 20 && y < 20;
                let s: f64 = if bright { 160.0 } else { 0.0 };
                (s * response[cfa.channel(x, y)] + 2.0).round() as u16
            })
            .collect();
        let g = grey_world_gains(&raw, w, cfa, 255.0 / 16.0).unwrap();
        // Over the bright cells: (160 + 2) / (96 + 2) and (160 + 2) / (128 + 2).
        assert!((g[0] - 162.0 / 98.0).abs() < 1e-12, "{cfa:?} {g:?}");
        assert!((g[2] - 162.0 / 130.0).abs() < 1e-12, "{cfa:?} {g:?}");
        // The whole frame's means would give 1.55 for red (1/0.6 = 1.67 is the truth).
        let mean = |c: usize| {
            let v: Vec<f64> = (0..w * h)
                .filter(|&i| cfa.channel(i % w, i / w) == c)
                .map(|i| f64::from(raw[i]))
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        assert!((mean(1) / mean(0) - 1.0 / 0.6).abs() > 0.1);
    }
    // Too few bright cells (one in 1024 when a thousandth is needed): not measured.
    let mut dark = vec![2u16; 64 * 64];
    dark[0..2].copy_from_slice(&[200, 200]);
    dark[64..66].copy_from_slice(&[200, 200]);
    assert_eq!(grey_world_gains(&dark, 64, Cfa::Rggb, 255.0 / 16.0), None);
}
