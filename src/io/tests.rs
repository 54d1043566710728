//! Tests of the readers and writers on files built here, on the real KITTI frames in
//! `../shared/data` when present, and on arbitrary bytes.

use std::io::{Cursor, Read};
use std::path::PathBuf;

use proptest::prelude::*;

use super::labels::LabelsWriter;
use super::npy::{self, NpyArray, NpyData};
use super::npz::NpzWriter;
use super::*;

// ---------- fixture builders ----------

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A small cloud with a flat, axis-aligned part (z = 0 ground) and exact-in-f32 values, so
/// every format must give back exactly these numbers.
fn sample_points() -> Vec<Point> {
    vec![[0.0, 0.0, 0.0], [1.5, -2.25, 0.0], [-3.0, 4.0, 0.0], [10.125, 0.5, 1.75], [-0.0625, 7.0, -1.5]]
}

/// ASCII PLY: a `camera` element before the vertices, extra vertex properties (uchar intensity,
/// a list), and a `face` element with lists after them.
fn ply_ascii(points: &[Point]) -> Vec<u8> {
    let mut s = String::from(
        "ply\nformat ascii 1.0\ncomment made by a test\nelement camera 1\nproperty float fx\nproperty list uchar int ids\n",
    );
    s += &format!(
        "element vertex {}\nproperty uchar intensity\nproperty float x\nproperty float y\nproperty list uchar float extra\nproperty float z\nproperty double nx\n",
        points.len()
    );
    s += "element face 2\nproperty list uchar int vertex_indices\nend_header\n";
    s += "500.0 3 1 2 3\n";
    for (i, p) in points.iter().enumerate() {
        s += &format!("{} {} {} 2 0.5 0.25 {} -1.0\n", i % 256, p[0], p[1], p[2]);
    }
    s += "3 0 1 2\n3 1 2 3\n";
    s.into_bytes()
}

/// Binary little-endian PLY with double x, y, z among other properties, an element before and
/// an element with lists after the vertices.
fn ply_binary_double(points: &[Point]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\nelement sensor 2\nproperty short id\nproperty list uchar uint beams\nelement vertex {}\nproperty double x\nproperty uint ring\nproperty double y\nproperty double z\nproperty uchar intensity\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n",
        points.len()
    );
    let mut b = header.into_bytes();
    for id in 0..2i16 {
        b.extend_from_slice(&id.to_le_bytes());
        b.push(2);
        b.extend_from_slice(&7u32.to_le_bytes());
        b.extend_from_slice(&8u32.to_le_bytes());
    }
    for (i, p) in points.iter().enumerate() {
        b.extend_from_slice(&(p[0] as f64).to_le_bytes());
        b.extend_from_slice(&(i as u32).to_le_bytes());
        b.extend_from_slice(&(p[1] as f64).to_le_bytes());
        b.extend_from_slice(&(p[2] as f64).to_le_bytes());
        b.push(200);
    }
    b.push(3);
    for i in 0..3i32 {
        b.extend_from_slice(&i.to_le_bytes());
    }
    b
}

/// Binary PLY with float x, y, z and a list property inside the vertex element (variable-size
/// records).
fn ply_binary_vertex_list(points: &[Point]) -> Vec<u8> {
    let header = format!(
        "ply\r\nformat binary_little_endian 1.0\r\nelement vertex {}\r\nproperty float x\r\nproperty list uchar ushort tags\r\nproperty float y\r\nproperty float z\r\nend_header\r\n",
        points.len()
    );
    let mut b = header.into_bytes();
    for (i, p) in points.iter().enumerate() {
        b.extend_from_slice(&p[0].to_le_bytes());
        b.push((i % 3) as u8);
        for t in 0..(i % 3) as u16 {
            b.extend_from_slice(&t.to_le_bytes());
        }
        b.extend_from_slice(&p[1].to_le_bytes());
        b.extend_from_slice(&p[2].to_le_bytes());
    }
    b
}

/// Binary PLY with only float x, y, z: 12 bytes per vertex.
fn ply_binary_xyz(n_declared: usize, data: &[u8]) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n_declared}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    )
    .into_bytes();
    b.extend_from_slice(data);
    b
}

fn pcd_ascii(points: &[Point]) -> Vec<u8> {
    let mut s = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity hist\nSIZE 4 4 4 4 2\nTYPE F F F F U\nCOUNT 1 1 1 1 2\nWIDTH {}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\nDATA ascii\n",
        points.len(),
        points.len()
    );
    for p in points {
        s += &format!("{} {} {} 0.5 3 4\n", p[0], p[1], p[2]);
    }
    s.into_bytes()
}

/// Binary PCD with float64 x, y, z after an integer field and before others, WIDTH x HEIGHT
/// giving the count (no POINTS line), and no `# .PCD` comment.
fn pcd_binary_f64(points: &[Point]) -> Vec<u8> {
    let mut b = format!(
        "VERSION .7\nFIELDS t x y z intensity _\nSIZE 4 8 8 8 4 1\nTYPE U F F F F U\nCOUNT 1 1 1 1 1 3\nWIDTH {}\nHEIGHT 1\nDATA binary\n",
        points.len()
    )
    .into_bytes();
    for (i, p) in points.iter().enumerate() {
        b.extend_from_slice(&(i as u32).to_le_bytes());
        for c in p {
            b.extend_from_slice(&(*c as f64).to_le_bytes());
        }
        b.extend_from_slice(&0.75f32.to_le_bytes());
        b.extend_from_slice(&[1, 2, 3]);
    }
    b
}

fn kitti_bin(points: &[Point]) -> Vec<u8> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p[0], p[1], p[2], 0.3]).collect();
    f32_bytes(&flat)
}

fn npy_f32_n4(points: &[Point]) -> Vec<u8> {
    let flat: Vec<f32> = points.iter().flat_map(|p| [p[0], p[1], p[2], 9.0]).collect();
    let mut b = Vec::new();
    npy::write_npy_f32(&mut b, &[points.len(), 4], &flat).unwrap();
    b
}

fn npy_f64_n4(points: &[Point]) -> Vec<u8> {
    let flat: Vec<f64> = points.iter().flat_map(|p| [p[0] as f64, p[1] as f64, p[2] as f64, -9.0]).collect();
    let mut b = Vec::new();
    npy::write_npy_f64(&mut b, &[points.len(), 4], &flat).unwrap();
    b
}

/// An `.npy` with a hand-written header dict (for headers our writer never produces).
fn npy_with_dict(dict: &str, data: &[u8]) -> Vec<u8> {
    let mut header = dict.to_owned();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(' ');
    }
    header.push('\n');
    let mut b = npy::MAGIC.to_vec();
    b.extend_from_slice(&[1, 0]);
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    b.extend_from_slice(data);
    b
}

fn all_good_fixtures() -> Vec<(&'static str, Vec<u8>)> {
    let p = sample_points();
    vec![
        ("a.ply", ply_ascii(&p)),
        ("b.ply", ply_binary_double(&p)),
        ("c.ply", ply_binary_vertex_list(&p)),
        ("a.pcd", pcd_ascii(&p)),
        ("b.pcd", pcd_binary_f64(&p)),
        ("k.bin", kitti_bin(&p)),
        ("a.npy", npy_f32_n4(&p)),
        ("b.npy", npy_f64_n4(&p)),
    ]
}

fn err_text(r: Result<Vec<Point>, ReadError>) -> String {
    match r {
        Ok(p) => panic!("expected an error, read {} points", p.len()),
        Err(e) => e.to_string(),
    }
}

// ---------- good files ----------

#[test]
fn every_good_fixture_reads_back_the_exact_points() {
    for (name, bytes) in all_good_fixtures() {
        let got = read_points(&bytes, Some(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got, sample_points(), "{name}");
    }
}

#[test]
fn every_good_fixture_is_detected_without_a_name() {
    let expected =
        [Format::Ply, Format::Ply, Format::Ply, Format::Pcd, Format::Pcd, Format::KittiBin, Format::Npy, Format::Npy];
    for ((name, bytes), want) in all_good_fixtures().into_iter().zip(expected) {
        assert_eq!(detect_format(&bytes, None).unwrap(), want, "{name}");
        assert_eq!(read_points(&bytes, None).unwrap(), sample_points(), "{name}");
    }
}

#[test]
fn empty_clouds_read_as_zero_points() {
    assert!(read_points(&ply_ascii(&[]), None).unwrap().is_empty());
    assert!(read_points(&ply_binary_double(&[]), None).unwrap().is_empty());
    assert!(read_points(&pcd_ascii(&[]), None).unwrap().is_empty());
    assert!(read_points(&pcd_binary_f64(&[]), None).unwrap().is_empty());
    assert!(read_points(&npy_f32_n4(&[]), None).unwrap().is_empty());
    assert!(read_points(&[], Some("000000.bin")).unwrap().is_empty());
}

#[test]
fn format_display_names_the_format() {
    assert_eq!(Format::Ply.to_string(), "PLY");
    assert_eq!(Format::Pcd.to_string(), "PCD");
    assert_eq!(Format::KittiBin.to_string(), "KITTI .bin");
    assert_eq!(Format::Npy.to_string(), "NPY");
}

// ---------- detection ----------

#[test]
fn content_wins_over_a_misleading_name() {
    let p = sample_points();
    assert_eq!(detect_format(&ply_ascii(&p), Some("cloud.pcd")).unwrap(), Format::Ply);
    assert_eq!(detect_format(&pcd_ascii(&p), Some("cloud.ply")).unwrap(), Format::Pcd);
    assert_eq!(detect_format(&npy_f32_n4(&p), Some("cloud.bin")).unwrap(), Format::Npy);
    assert_eq!(detect_format(&pcd_binary_f64(&p), Some("x.npy")).unwrap(), Format::Pcd);
    assert_eq!(detect_format(&kitti_bin(&p), Some("cloud.ply")).unwrap(), Format::KittiBin);
    assert_eq!(read_points(&npy_f64_n4(&p), Some("scan.pcd")).unwrap(), p);
}

#[test]
fn headerless_bytes_that_are_not_plausible_points_are_unknown() {
    // 0x7f7f7f7f is about 3.4e38 m: finite but not a LiDAR return.
    let huge = vec![0x7fu8; 64];
    assert!(matches!(detect_format(&huge, None), Err(ReadError::UnknownFormat { .. })));
    assert!(matches!(detect_format(b"hello world, 1 2 3\n", Some("notes.txt")), Err(ReadError::UnknownFormat { .. })));
    assert!(matches!(detect_format(&[], None), Err(ReadError::UnknownFormat { .. })));
    // With a .bin name the same bytes are KITTI, and as such they are fine (finite).
    assert_eq!(detect_format(&huge, Some("x.BIN")).unwrap(), Format::KittiBin);
}

#[test]
fn a_name_picks_the_reader_that_explains_what_is_wrong() {
    let text = err_text(read_points(b"garbage that is no header", Some("scan.ply")));
    assert_eq!(text, "PLY header: missing 'ply' magic line");
    let text = err_text(read_points(b"garbage that is no header", Some("scan.npy")));
    assert!(text.starts_with("NPY header"), "{text}");
    let text = err_text(read_points(b"garbage that is no header", Some("scan.pcd")));
    assert!(text.starts_with("PCD header"), "{text}");
}

// ---------- PLY errors ----------

#[test]
fn ply_without_end_header_is_rejected() {
    let text = err_text(read_points(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n", None));
    assert_eq!(text, "PLY header: missing 'end_header'");
}

#[test]
fn truncated_binary_ply_says_how_many_bytes_are_missing() {
    let data = vec![0u8; 11000];
    let text = err_text(read_points(&ply_binary_xyz(1000, &data), None));
    assert_eq!(text, "file truncated: expected 12000 bytes of vertex data, got 11000");
}

#[test]
fn a_lying_vertex_count_is_caught_before_allocating() {
    // 10^15 vertices would need 12 PB; the check must come before any allocation.
    let err = read_points(&ply_binary_xyz(1_000_000_000_000_000, &[0u8; 24]), None).unwrap_err();
    assert!(matches!(err, ReadError::Truncated { got: 24, .. }), "{err}");
    let err = read_points(&ply_binary_xyz(usize::MAX, &[0u8; 24]), None).unwrap_err();
    assert!(matches!(err, ReadError::Truncated { .. }), "{err}");
    let ascii = b"ply\nformat ascii 1.0\nelement vertex 999999999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n";
    let err = read_points(ascii, None).unwrap_err();
    assert!(matches!(err, ReadError::Truncated { got: 1, .. }), "{err}");
}

#[test]
fn ply_with_nan_or_inf_names_the_point() {
    let mut p = sample_points();
    p[3][1] = f32::NAN;
    assert_eq!(err_text(read_points(&ply_ascii(&p), None)), "point 3 has a non-finite coordinate");
    let mut data = f32_bytes(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    data[20..24].copy_from_slice(&f32::INFINITY.to_le_bytes());
    assert_eq!(err_text(read_points(&ply_binary_xyz(2, &data), None)), "point 1 has a non-finite coordinate");
}

#[test]
fn a_double_beyond_f32_range_is_non_finite() {
    let mut p = ply_binary_double(&sample_points());
    // First vertex x sits right after the header and the two sensor records (2 + 1 + 8 bytes each).
    let start = p.windows(11).position(|w| w == b"end_header\n").unwrap() + 11 + 2 * 11;
    p[start..start + 8].copy_from_slice(&1e300f64.to_le_bytes());
    assert_eq!(err_text(read_points(&p, None)), "point 0 has a non-finite coordinate");
}

#[test]
fn big_endian_ply_is_unsupported() {
    let b = b"ply\nformat binary_big_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    let err = read_points(b, None).unwrap_err();
    assert!(matches!(err, ReadError::Unsupported { format: Format::Ply, .. }), "{err}");
    assert!(err.to_string().contains("binary_big_endian"));
}

#[test]
fn ply_header_problems_are_named() {
    let cases: [(&[u8], &str); 6] = [
        (b"ply\nelement vertex 0\nproperty float x\nend_header\n", "missing 'format' line"),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n", "no 'vertex' element"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nend_header\n",
            "no property 'z'",
        ),
        (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", "is not a count"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quaternion x\nend_header\n", "unknown property type"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "property before any element"),
    ];
    for (bytes, want) in cases {
        let text = err_text(read_points(bytes, None));
        assert!(text.starts_with("PLY header") && text.contains(want), "{text:?} lacks {want:?}");
    }
}

#[test]
fn integer_ply_coordinates_are_rejected_clearly() {
    let b = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty int x\nproperty float y\nproperty float z\nend_header\n1 2 3\n";
    let err = read_points(b, None).unwrap_err();
    assert!(matches!(err, ReadError::Unsupported { .. }), "{err}");
    assert!(err.to_string().contains("'x'"), "{err}");
}

#[test]
fn ascii_ply_with_a_word_for_a_coordinate_or_missing_lines_fails() {
    let b = b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n4 five 6\n";
    assert_eq!(err_text(read_points(b, None)), "PLY data: vertex 1: 'five' is not a number");
    let b = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n4 5 6\n";
    assert_eq!(err_text(read_points(b, None)), "file truncated: expected 3 vertices, got 2");
}

#[test]
fn ply_element_before_vertex_that_runs_out_is_truncation() {
    let b = b"ply\nformat binary_little_endian 1.0\nelement face 5\nproperty list uchar int v\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n\x03\x00\x00\x00\x00";
    assert_eq!(err_text(read_points(b, None)), "file truncated: expected 5 'face' records, got 0");
}

// ---------- PCD errors ----------

#[test]
fn binary_compressed_pcd_is_unsupported() {
    let b = b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n\x00\x00";
    let err = read_points(b, None).unwrap_err();
    assert!(matches!(err, ReadError::Unsupported { format: Format::Pcd, .. }), "{err}");
    assert!(err.to_string().contains("binary_compressed"));
}

#[test]
fn truncated_and_lying_pcd_are_rejected() {
    let p = sample_points();
    let full = pcd_binary_f64(&p);
    let err = read_points(&full[..full.len() - 5], None).unwrap_err();
    // 4 + 3 * 8 + 4 + 3 = 35 bytes per point.
    assert_eq!(err.to_string(), format!("file truncated: expected {} bytes of point data, got {}", 35 * 5, 35 * 5 - 5));
    let lying = String::from_utf8(pcd_ascii(&p))
        .unwrap()
        .replace("WIDTH 5", "WIDTH 4000000000000")
        .replace("POINTS 5", "POINTS 4000000000000");
    let err = read_points(lying.as_bytes(), None).unwrap_err();
    assert!(matches!(err, ReadError::Truncated { got: 5, .. }), "{err}");
    let fewer = String::from_utf8(pcd_ascii(&p)).unwrap().replace("POINTS 5", "POINTS 4").replace("WIDTH 5", "WIDTH 4");
    assert!(err_text(read_points(fewer.as_bytes(), None)).contains("more than the 4 declared points"));
    let disagree = String::from_utf8(pcd_ascii(&p)).unwrap().replace("POINTS 5", "POINTS 6");
    assert!(err_text(read_points(disagree.as_bytes(), None)).contains("disagrees with WIDTH x HEIGHT"));
}

#[test]
fn pcd_header_and_data_problems_are_named() {
    let cases: [(&[u8], &str); 7] = [
        (b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 0\n", "PCD header: missing 'DATA' line"),
        (b"VERSION .7\nFIELDS x y z\nSIZE 4 4\nTYPE F F F\nPOINTS 0\nDATA ascii\n", "SIZE has 2 entries for 3 FIELDS"),
        (b"VERSION .7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nPOINTS 0\nDATA ascii\n", "FIELDS has no 'z'"),
        (b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE I F F\nPOINTS 0\nDATA ascii\n", "field 'x' of type"),
        (b"VERSION .7\nFIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nPOINTS 0\nDATA ascii\n", "TYPE F with SIZE 3"),
        (
            b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 2\n",
            "line 7: expected 3 values, got 2",
        ),
        (b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 2 zz\n", "'zz' is not a number"),
    ];
    for (bytes, want) in cases {
        let text = err_text(read_points(bytes, None));
        assert!(text.contains(want), "{text:?} lacks {want:?}");
    }
}

#[test]
fn pcd_with_nan_names_the_point() {
    let b = b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 3\nDATA ascii\n1 2 3\n4 5 6\nnan 0 0\n";
    assert_eq!(err_text(read_points(b, None)), "point 2 has a non-finite coordinate");
}

// ---------- KITTI errors ----------

#[test]
fn kitti_length_not_a_multiple_of_16_is_rejected() {
    let mut b = kitti_bin(&sample_points());
    b.pop();
    let text = err_text(read_points(&b, Some("000000.bin")));
    assert!(text.contains("length 79 bytes is not a multiple of 16"), "{text}");
}

#[test]
fn kitti_with_nan_names_the_point() {
    let mut p = sample_points();
    p[4][2] = f32::NAN;
    assert_eq!(err_text(read_points(&kitti_bin(&p), Some("a.bin"))), "point 4 has a non-finite coordinate");
    // Without the name a NaN-bearing file is not plausible KITTI either.
    assert!(matches!(read_points(&kitti_bin(&p), None), Err(ReadError::UnknownFormat { .. })));
}

#[test]
fn real_kitti_frames_read_to_their_record_count() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/kitti-odometry-00");
    if !dir.is_dir() {
        eprintln!("skipped: {} is absent", dir.display());
        return;
    }
    let points = read_points_file(&dir.join("000000.bin")).unwrap();
    // 1 994 688 bytes / 16 bytes per record.
    assert_eq!(points.len(), 124_668);
    // Velodyne HDL-64E: returns within ~120 m, sensor ~1.73 m above the road.
    assert!(points.iter().all(|p| p.iter().all(|c| c.abs() < 150.0)));
    let mut zs: Vec<f32> = points.iter().map(|p| p[2]).collect();
    zs.sort_by(f32::total_cmp);
    let median_z = zs[zs.len() / 2];
    assert!((-2.5..0.5).contains(&median_z), "median z {median_z}");
    for k in 1..6 {
        let path = dir.join(format!("{k:06}.bin"));
        let len = std::fs::metadata(&path).unwrap().len() as usize;
        assert_eq!(read_points_file(&path).unwrap().len(), len / 16, "{}", path.display());
        // Content alone identifies these files too.
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(detect_format(&bytes, None).unwrap(), Format::KittiBin);
    }
}

#[test]
fn a_missing_file_error_names_the_path() {
    let err = read_points_file(std::path::Path::new("/nonexistent/dir/scan.ply")).unwrap_err();
    assert!(matches!(err, ReadError::Io { .. }));
    assert!(err.to_string().contains("/nonexistent/dir/scan.ply"), "{err}");
}

#[test]
fn read_points_file_uses_the_file_name_as_hint() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("scan.bin");
    std::fs::write(&path, vec![0x7fu8; 32]).unwrap();
    // Implausible as content, but the name says KITTI.
    assert_eq!(read_points_file(&path).unwrap().len(), 2);
}

// ---------- NPY ----------

#[test]
fn npy_header_is_aligned_and_parsable() {
    for shape in [&[][..], &[7][..], &[3, 4][..], &[2, 3, 5][..]] {
        let h = npy::npy_header(npy::DType::F64, shape);
        assert_eq!(h.len() % 64, 0);
        assert_eq!(h.last(), Some(&b'\n'));
        let n: usize = shape.iter().product();
        let mut b = h.clone();
        b.extend(std::iter::repeat_n(0u8, n * 8));
        assert_eq!(npy::read_npy(&b).unwrap().shape, shape);
    }
    assert_eq!(npy::shape_text(&[]), "()");
    assert_eq!(npy::shape_text(&[5]), "(5,)");
    assert_eq!(npy::shape_text(&[5, 3]), "(5, 3)");
}

#[test]
fn every_npy_dtype_round_trips() {
    let shape = [2, 3];
    let cases: Vec<(Vec<u8>, NpyData)> = vec![
        (
            write(|b| npy::write_npy_f32(b, &shape, &[1.0, -2.0, 3.5, 0.0, 1e-30, 7.0])),
            NpyData::F32(vec![1.0, -2.0, 3.5, 0.0, 1e-30, 7.0]),
        ),
        (
            write(|b| npy::write_npy_f64(b, &shape, &[1.0, -2.0, 3.5, 0.0, 1e-300, 7.0])),
            NpyData::F64(vec![1.0, -2.0, 3.5, 0.0, 1e-300, 7.0]),
        ),
        (
            write(|b| npy::write_npy_i32(b, &shape, &[1, -2, 3, i32::MIN, i32::MAX, 0])),
            NpyData::I32(vec![1, -2, 3, i32::MIN, i32::MAX, 0]),
        ),
        (write(|b| npy::write_npy_u8(b, &shape, &[0, 1, 2, 254, 255, 9])), NpyData::U8(vec![0, 1, 2, 254, 255, 9])),
        (
            write(|b| npy::write_npy_bool(b, &shape, &[true, false, true, true, false, false])),
            NpyData::Bool(vec![true, false, true, true, false, false]),
        ),
    ];
    for (bytes, data) in cases {
        assert_eq!(npy::read_npy(&bytes).unwrap(), NpyArray { shape: shape.to_vec(), data });
    }
}

fn write(f: impl FnOnce(&mut Vec<u8>) -> Result<(), WriteError>) -> Vec<u8> {
    let mut b = Vec::new();
    f(&mut b).unwrap();
    b
}

#[test]
fn fortran_order_npy_is_transposed_to_c_order() {
    // C-order array a[i][j][k] = 100 i + 10 j + k of shape (2, 3, 4), stored column-major.
    let shape = [2usize, 3, 4];
    let mut f_order = Vec::new();
    for k in 0..4 {
        for j in 0..3 {
            for i in 0..2 {
                f_order.push((100 * i + 10 * j + k) as f32);
            }
        }
    }
    let b = npy_with_dict("{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3, 4), }", &f32_bytes(&f_order));
    let arr = npy::read_npy(&b).unwrap();
    let want: Vec<f32> = (0..24).map(|n| (100 * (n / 12) + 10 * (n / 4 % 3) + n % 4) as f32).collect();
    assert_eq!(arr, NpyArray { shape: shape.to_vec(), data: NpyData::F32(want) });
    // And as points: a Fortran-order (2, 3) array.
    let b = npy_with_dict(
        "{'descr': '<f4', 'fortran_order': True, 'shape': (2, 3)}",
        &f32_bytes(&[1.0, 4.0, 2.0, 5.0, 3.0, 6.0]),
    );
    assert_eq!(read_points(&b, None).unwrap(), vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
}

#[test]
fn npy_point_arrays_of_the_wrong_type_or_shape_are_rejected() {
    let ints = write(|b| npy::write_npy_i32(b, &[2, 3], &[1, 2, 3, 4, 5, 6]));
    let err = read_points(&ints, None).unwrap_err();
    assert!(matches!(err, ReadError::Unsupported { .. }) && err.to_string().contains("<i4"), "{err}");
    let two_cols = write(|b| npy::write_npy_f32(b, &[3, 2], &[0.0; 6]));
    assert!(err_text(read_points(&two_cols, None)).contains("not (N, C) with C >= 3"));
    let flat = write(|b| npy::write_npy_f32(b, &[6], &[0.0; 6]));
    assert!(err_text(read_points(&flat, None)).contains("[6]"));
    let big_endian = npy_with_dict("{'descr': '>f4', 'fortran_order': False, 'shape': (1, 3), }", &[0; 12]);
    assert!(err_text(read_points(&big_endian, None)).contains("big-endian"));
    let half = npy_with_dict("{'descr': '<f2', 'fortran_order': False, 'shape': (1, 3), }", &[0; 6]);
    assert_eq!(err_text(read_points(&half, None)), "unsupported NPY: dtype '<f2'");
    let structured =
        npy_with_dict("{'descr': [('x', '<f4'), ('y', '<f4')], 'fortran_order': False, 'shape': (1,), }", &[0; 8]);
    assert!(err_text(read_points(&structured, None)).contains("structured dtype"));
}

#[test]
fn truncated_lying_or_garbled_npy_is_rejected() {
    let good = npy_f32_n4(&sample_points());
    assert_eq!(
        err_text(read_points(&good[..good.len() - 4], None)),
        "file truncated: expected 80 bytes of array data, got 76"
    );
    let lying = npy_with_dict("{'descr': '<f4', 'fortran_order': False, 'shape': (100000000000000, 3), }", &[0; 12]);
    assert!(matches!(read_points(&lying, None), Err(ReadError::Truncated { got: 12, .. })));
    let overflow = npy_with_dict(
        "{'descr': '<f8', 'fortran_order': False, 'shape': (18446744073709551615, 18446744073709551615), }",
        &[],
    );
    assert!(err_text(read_points(&overflow, None)).contains("overflows"));
    let mut trailing = good.clone();
    trailing.push(0);
    assert!(err_text(read_points(&trailing, None)).contains("1 trailing bytes"));
    let garbled = npy_with_dict("{'descr' '<f4', 'fortran_order': False, 'shape': (1, 3), }", &[0; 12]);
    assert!(err_text(read_points(&garbled, None)).starts_with("NPY header"));
    let no_shape = npy_with_dict("{'descr': '<f4', 'fortran_order': False}", &[0; 12]);
    assert!(err_text(read_points(&no_shape, None)).contains("'shape'"));
    let mut short_header = good.clone();
    short_header.truncate(40);
    assert!(matches!(read_points(&short_header, None), Err(ReadError::Truncated { .. })));
    let bad_bool = npy_with_dict("{'descr': '|b1', 'fortran_order': False, 'shape': (2,), }", &[1, 7]);
    assert!(npy::read_npy(&bad_bool).unwrap_err().to_string().contains("byte value 7"));
}

#[test]
fn npy_nan_names_the_point() {
    let mut p = sample_points();
    p[2][0] = f32::NEG_INFINITY;
    assert_eq!(err_text(read_points(&npy_f32_n4(&p), None)), "point 2 has a non-finite coordinate");
}

#[test]
fn python2_style_long_shapes_are_read() {
    let b =
        npy_with_dict("{'descr': '<f4', 'fortran_order': False, 'shape': (1L, 3L), }", &f32_bytes(&[1.0, 2.0, 3.0]));
    assert_eq!(read_points(&b, None).unwrap(), vec![[1.0, 2.0, 3.0]]);
}

// ---------- NPZ ----------

/// Reads every entry of a zip as (name, bytes), in archive order.
fn unzip(bytes: &[u8]) -> Vec<(String, Vec<u8>)> {
    let mut archive = zip::ZipArchive::new(Cursor::new(bytes)).unwrap();
    (0..archive.len())
        .map(|i| {
            let mut f = archive.by_index(i).unwrap();
            assert_eq!(f.compression(), zip::CompressionMethod::Deflated);
            let mut data = Vec::new();
            f.read_to_end(&mut data).unwrap();
            (f.name().to_owned(), data)
        })
        .collect()
}

fn sample_npz() -> Vec<u8> {
    let mut w = NpzWriter::new(Cursor::new(Vec::new()));
    w.add_f32("points", &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
    w.add_f64("times", &[3], &[0.0, 0.1, 0.2]).unwrap();
    w.add_i32("labels", &[2, 2], &[-1, 0, 1, 2]).unwrap();
    w.add_u8("classes", &[4], &[0, 1, 2, 255]).unwrap();
    w.add_bool("mask", &[2, 1], &[true, false]).unwrap();
    w.add_f32("empty", &[0, 3], &[]).unwrap();
    w.finish().unwrap().into_inner()
}

#[test]
fn npz_entries_round_trip_through_the_npy_reader() {
    let entries = unzip(&sample_npz());
    let names: Vec<&str> = entries.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["points.npy", "times.npy", "labels.npy", "classes.npy", "mask.npy", "empty.npy"]);
    let arrays: Vec<NpyArray> = entries.iter().map(|(_, b)| npy::read_npy(b).unwrap()).collect();
    assert_eq!(arrays[0], NpyArray { shape: vec![2, 3], data: NpyData::F32(vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) });
    assert_eq!(arrays[1], NpyArray { shape: vec![3], data: NpyData::F64(vec![0.0, 0.1, 0.2]) });
    assert_eq!(arrays[2], NpyArray { shape: vec![2, 2], data: NpyData::I32(vec![-1, 0, 1, 2]) });
    assert_eq!(arrays[3], NpyArray { shape: vec![4], data: NpyData::U8(vec![0, 1, 2, 255]) });
    assert_eq!(arrays[4], NpyArray { shape: vec![2, 1], data: NpyData::Bool(vec![true, false]) });
    assert_eq!(arrays[5], NpyArray { shape: vec![0, 3], data: NpyData::F32(vec![]) });
}

#[test]
fn npz_rejects_bad_shapes_and_names() {
    let mut w = NpzWriter::new(Cursor::new(Vec::new()));
    let err = w.add_f32("a", &[2, 3], &[0.0; 5]).unwrap_err();
    assert_eq!(err.to_string(), "array 'a': shape [2, 3] needs 6 elements, got 5");
    w.add_f32("a", &[1], &[0.0]).unwrap();
    assert!(matches!(w.add_f64("a", &[1], &[0.0]), Err(WriteError::InvalidName { .. })));
    assert!(matches!(w.add_u8("", &[1], &[0]), Err(WriteError::InvalidName { .. })));
    assert!(matches!(w.add_i32("o", &[usize::MAX, 2], &[]), Err(WriteError::ShapeMismatch { .. })));
    // The failed calls left the archive valid, holding only "a".
    let bytes = w.finish().unwrap().into_inner();
    assert_eq!(unzip(&bytes).len(), 1);
}

#[test]
fn read_npz_gives_back_what_the_writer_wrote() {
    let mut w = NpzWriter::new(Cursor::new(Vec::new()));
    w.add_f32("points", &[2, 3], &[1.0, 2.0, 3.0, 4.0, f32::NAN, 6.0]).unwrap();
    w.add_f64("times", &[3], &[0.0, 0.1, 0.2]).unwrap();
    w.add_i32("labels", &[2, 2], &[-1, 0, 1, 2]).unwrap();
    w.add_i64("index", &[3], &[0, -5, i64::MAX]).unwrap();
    w.add_u8("classes", &[4], &[0, 1, 2, 255]).unwrap();
    w.add_bool("mask", &[2, 1], &[true, false]).unwrap();
    w.add_f32("empty", &[0, 3], &[]).unwrap();
    let arrays = npz::read_npz(&w.finish().unwrap().into_inner()).unwrap();
    let names: Vec<&str> = arrays.keys().map(String::as_str).collect();
    assert_eq!(names, ["classes", "empty", "index", "labels", "mask", "points", "times"]);
    // NaN != NaN: compare the f32 payload bit for bit.
    let NpyData::F32(points) = &arrays["points"].data else { panic!("points: {:?}", arrays["points"]) };
    let bits: Vec<u32> = points.iter().map(|v| v.to_bits()).collect();
    let want: Vec<u32> = [1.0f32, 2.0, 3.0, 4.0, f32::NAN, 6.0].iter().map(|v| v.to_bits()).collect();
    assert_eq!((arrays["points"].shape.as_slice(), bits), ([2usize, 3].as_slice(), want));
    assert_eq!(arrays["times"], NpyArray { shape: vec![3], data: NpyData::F64(vec![0.0, 0.1, 0.2]) });
    assert_eq!(arrays["labels"], NpyArray { shape: vec![2, 2], data: NpyData::I32(vec![-1, 0, 1, 2]) });
    assert_eq!(arrays["index"], NpyArray { shape: vec![3], data: NpyData::I64(vec![0, -5, i64::MAX]) });
    assert_eq!(arrays["classes"], NpyArray { shape: vec![4], data: NpyData::U8(vec![0, 1, 2, 255]) });
    assert_eq!(arrays["mask"], NpyArray { shape: vec![2, 1], data: NpyData::Bool(vec![true, false]) });
    assert_eq!(arrays["empty"], NpyArray { shape: vec![0, 3], data: NpyData::F32(vec![]) });
}

/// A zip written directly, so the reader sees entries the npz writer would never produce.
fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
    use std::io::Write;
    let mut z = zip::ZipWriter::new(Cursor::new(Vec::new()));
    for (name, data) in entries {
        z.start_file(*name, zip::write::SimpleFileOptions::default()).unwrap();
        z.write_all(data).unwrap();
    }
    z.finish().unwrap().into_inner()
}

#[test]
fn read_npz_rejects_malformed_archives_with_a_clear_error() {
    use npz::{NpzReadError, read_npz};
    let msg = |r: Result<_, NpzReadError>| r.unwrap_err().to_string();
    assert!(msg(read_npz(b"not a zip at all")).starts_with("not a readable .npz (zip) archive"));
    assert!(msg(read_npz(&[])).starts_with("not a readable .npz (zip) archive"));
    // A truncated archive (its central directory cut off) is not readable either.
    let mut good = NpzWriter::new(Cursor::new(Vec::new()));
    good.add_f32("a", &[3], &[1.0, 2.0, 3.0]).unwrap();
    let good = good.finish().unwrap().into_inner();
    assert!(msg(read_npz(&good[..good.len() - 10])).starts_with("not a readable .npz (zip) archive"));
    assert_eq!(msg(read_npz(&zip_of(&[("readme.txt", b"hello")]))), ".npz entry 'readme.txt' is not a NAME.npy array");
    let e = msg(read_npz(&zip_of(&[("a.npy", b"\x93NUMPY garbage")])));
    assert_eq!(e, ".npz array 'a': unsupported NPY: format version 32");
    // One f32 announced as (2,), 4 bytes present: truncated, named.
    let mut short = npy::npy_header(npy::DType::F32, &[2]);
    short.extend_from_slice(&1.0f32.to_le_bytes());
    let e = msg(read_npz(&zip_of(&[("b.npy", &short)])));
    assert_eq!(e, ".npz array 'b': file truncated: expected 8 bytes of array data, got 4");
}

/// Found by fuzzing (fuzz target `npz`): a 371-byte archive whose second entry declares
/// 4,177,526,631 uncompressed bytes. The reader reserved the declared size before reading, a
/// 3.9 GB allocation for a few hundred bytes; now the reservation is capped by what the archive
/// can inflate to and the archive is refused with a clear error.
const NPZ_DECLARING_4_GB: &[u8] =
    b"PK\x03\x04\x14\x00\x00\x00\x08\x00\x03-\x85]\x0dZ\x19\x0d_\x00\x00\x00\xb0\x00\x00\x00\x06\
      \x00\x00\x00pc.npy\x9b\xec\x17\xea\x1b\x10\xc9\xc8P\xc6P\xad\x9e\x92Z\x9c\x5c\xa4n\xa5\xa0n\
      \x93f\xa2\xae\xa3\xa0\x9e\x96_TR\x94\x98\x17\x9f_\x94\x92\x0a\x12wK\xcc)N\x05\x8a\x17g$\x16\
      \xa4\x02\xf9\x1a&:\x0a\xc6\x9a:\x0a\xb5\x0ad\x03.\x06\x14p\xc0\x9e\x81A\xe0\x00\x84\xed\x00\
      \xa4\x1b\x1c l%G \x01\x94{`\x0f\x00PK\x03\x04P\xc6P\xad\x9e\x92Z\x9c\x5c\xa4n\xa5\xa0n\x93f\
      \xa2\xae\xa3\xa0\x9e\x96_TR\x94\x98\x17\x9f_\x94\x92\x0a\x12wK\xcc)N\x05\x8a\x17g$\x16\xa4\
      \x02\xf9\x1a&:\x0a\xc6\x9a:\x0a\xb5\x0ad\x03.\x06\x14p\xc0\x9e\x81A\xe0\x00\x84\xed\x00\xa4\
      \x1b\x1c \xcc)N\x05\x8a\x17g$\x16\xa4\x02\xf9\x1a\xc6:\x9a:\x0a\xb5\x0a\x14\x00\xae\xffP\xc0\
      \x00\x05\xecP\x1a\x00PK\x01\x02\x14\x03\x14p\x00\x00\x08\x00\x03-\x85]\x0dZ\x19\x0d_\x00\x00\
      \x00\xb0\x00\x00\x00\x06\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x80\x01\x00\x00\x00\x00\
      pc.npyPK\x01\x02\x14\x03\x14\x00\x00\x00\x08\x00\x03-\x85]\xaf\x8e\x8e\xa0\xb4\xff\xff\xffg\
      \xff\xff\xf8\x07\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x00\x80\x01\x83\x00\x00\x00idx.npyP\
      K\x05\x06\x00\x00\x00\x00\x02\x00\x02\x00i\x00\x00\x00\xf4\x00\x00\x00\x00\x00";

#[test]
fn npz_entry_declaring_gigabytes_reserves_only_what_the_archive_can_hold() {
    let len = NPZ_DECLARING_4_GB.len();
    assert_eq!(npz::entry_capacity(4_177_526_631, len), len * 1032);
    assert_eq!(npz::entry_capacity(100, len), 100);
    let e = npz::read_npz(NPZ_DECLARING_4_GB).unwrap_err().to_string();
    assert_eq!(e, ".npz entry 'idx': incomplete deflate stream");
}

/// A Python interpreter that can import numpy: the one on PATH, else the system one (a pyenv
/// shim may shadow a distribution's numpy).
fn python_with_numpy() -> Option<&'static str> {
    ["python3", "/usr/bin/python3"].into_iter().find(|py| {
        std::process::Command::new(py).args(["-c", "import numpy"]).output().is_ok_and(|o| o.status.success())
    })
}

fn run_python(py: &str, script: &str, arg: &std::path::Path) {
    let out = std::process::Command::new(py).arg("-c").arg(script).arg(arg).output().unwrap();
    assert!(
        out.status.success(),
        "python failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn numpy_load_reads_the_npz() {
    let Some(py) = python_with_numpy() else {
        eprintln!("skipped: no python3 with numpy");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sample.npz");
    std::fs::write(&path, sample_npz()).unwrap();
    let script = "import sys, numpy as np\n\
        z = np.load(sys.argv[1])\n\
        assert sorted(z.files) == ['classes', 'empty', 'labels', 'mask', 'points', 'times'], z.files\n\
        assert z['points'].dtype == np.float32 and z['points'].shape == (2, 3)\n\
        assert z['points'].tolist() == [[1, 2, 3], [4, 5, 6]]\n\
        assert z['times'].dtype == np.float64 and z['times'].tolist() == [0.0, 0.1, 0.2]\n\
        assert z['labels'].dtype == np.int32 and z['labels'].tolist() == [[-1, 0], [1, 2]]\n\
        assert z['classes'].dtype == np.uint8 and z['classes'].tolist() == [0, 1, 2, 255]\n\
        assert z['mask'].dtype == np.bool_ and z['mask'].tolist() == [[True], [False]]\n\
        assert z['empty'].shape == (0, 3) and z['empty'].dtype == np.float32\n";
    run_python(py, script, &path);
}

#[test]
fn numpy_save_output_is_read_by_read_npy_and_read_points() {
    let Some(py) = python_with_numpy() else {
        eprintln!("skipped: no python3 with numpy");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let script = "import sys, os, numpy as np\n\
        d = sys.argv[1]\n\
        a = np.arange(12, dtype=np.float64).reshape(3, 4) * 0.5\n\
        np.save(os.path.join(d, 'c.npy'), a)\n\
        np.save(os.path.join(d, 'f.npy'), np.asfortranarray(a.astype(np.float32)))\n\
        np.save(os.path.join(d, 'b.npy'), np.array([[True, False], [False, True]]))\n\
        np.save(os.path.join(d, 'u.npy'), np.arange(5, dtype=np.uint8))\n\
        np.save(os.path.join(d, 'i.npy'), np.arange(-2, 4, dtype=np.int32).reshape(2, 3, 1))\n";
    run_python(py, script, dir.path());
    let want: Vec<Point> = (0..3).map(|i| [i as f32 * 2.0, i as f32 * 2.0 + 0.5, i as f32 * 2.0 + 1.0]).collect();
    assert_eq!(read_points_file(&dir.path().join("c.npy")).unwrap(), want);
    assert_eq!(read_points_file(&dir.path().join("f.npy")).unwrap(), want);
    let read = |n: &str| npy::read_npy(&std::fs::read(dir.path().join(n)).unwrap()).unwrap();
    assert_eq!(read("b.npy"), NpyArray { shape: vec![2, 2], data: NpyData::Bool(vec![true, false, false, true]) });
    assert_eq!(read("u.npy"), NpyArray { shape: vec![5], data: NpyData::U8(vec![0, 1, 2, 3, 4]) });
    assert_eq!(read("i.npy"), NpyArray { shape: vec![2, 3, 1], data: NpyData::I32(vec![-2, -1, 0, 1, 2, 3]) });
}

#[test]
fn python_zipfile_and_literal_eval_read_the_npz() {
    // Without numpy, check what numpy.load relies on: Python's zipfile opens the archive and
    // each header is a Python literal with the data right after it, 64-byte aligned.
    let py = "python3";
    if std::process::Command::new(py).arg("--version").output().is_err() {
        eprintln!("skipped: no python3");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sample.npz");
    std::fs::write(&path, sample_npz()).unwrap();
    let script = "import sys, zipfile, ast, struct\n\
        z = zipfile.ZipFile(sys.argv[1])\n\
        assert z.testzip() is None\n\
        b = z.read('points.npy')\n\
        assert b[:8] == b'\\x93NUMPY\\x01\\x00'\n\
        n = struct.unpack('<H', b[8:10])[0]\n\
        h = ast.literal_eval(b[10:10 + n].decode('latin1'))\n\
        assert h == {'descr': '<f4', 'fortran_order': False, 'shape': (2, 3)}, h\n\
        assert (10 + n) % 64 == 0\n\
        assert struct.unpack('<6f', b[10 + n:]) == (1, 2, 3, 4, 5, 6)\n";
    run_python(py, script, &path);
}

// ---------- labels ----------

#[test]
fn labels_npz_holds_one_flow_per_pair_the_object_ids_of_every_frame_and_the_timestamps() {
    let flows = [sample_points(), vec![], vec![[0.5, -0.5, 0.25]]];
    let times = [0.0, 0.1, 0.2, 0.3];
    let ids = [vec![-1, 0, 0, -1, 3], vec![], vec![2], vec![-1, -1]];
    let mut w = labels::LabelsNpzWriter::new(Cursor::new(Vec::new()));
    for (k, frame_ids) in ids.iter().enumerate() {
        w.frame(flows.get(k).map(Vec::as_slice), frame_ids).unwrap();
    }
    let bytes = w.finish(&times).unwrap().into_inner();
    let entries: std::collections::BTreeMap<String, Vec<u8>> = unzip(&bytes).into_iter().collect();
    let names: Vec<&str> = entries.keys().map(String::as_str).collect();
    assert_eq!(
        names,
        [
            "flow_000.npy",
            "flow_001.npy",
            "flow_002.npy",
            "object_000.npy",
            "object_001.npy",
            "object_002.npy",
            "object_003.npy",
            "timestamps.npy"
        ]
    );
    for (k, frame_ids) in ids.iter().enumerate() {
        let arr = npy::read_npy(&entries[&format!("object_{k:03}.npy")]).unwrap();
        assert_eq!(arr, NpyArray { shape: vec![frame_ids.len()], data: NpyData::I32(frame_ids.clone()) });
    }
    for (k, flow) in flows.iter().enumerate() {
        let bytes = &entries[&format!("flow_{k:03}.npy")];
        let arr = npy::read_npy(bytes).unwrap();
        assert_eq!(arr, NpyArray { shape: vec![flow.len(), 3], data: NpyData::F32(flow.as_flattened().to_vec()) });
        // A flow file is a valid point file as well.
        assert_eq!(&read_points(bytes, None).unwrap(), flow);
    }
    assert_eq!(npy::read_npy(&entries["timestamps.npy"]).unwrap().data, NpyData::F64(times.to_vec()));
}

#[test]
fn labels_npz_refuses_object_ids_that_do_not_match_the_flow() {
    let mut w = labels::LabelsNpzWriter::new(Cursor::new(Vec::new()));
    let err = w.frame(Some(&sample_points()), &[-1]).unwrap_err();
    assert!(err.to_string().contains("frame 0"), "{err}");
}

#[test]
fn one_frame_npz_labels_hold_flow_validity_and_objects() {
    let flow = sample_points();
    let ids = [-1, 2, 2, -1, 0];
    let bytes = labels::write_flow_npz(Cursor::new(Vec::new()), &flow, None, Some(&ids)).unwrap().into_inner();
    let arrays = npz::read_npz(&bytes).unwrap();
    assert_eq!(arrays["flow"], NpyArray { shape: vec![5, 3], data: NpyData::F32(flow.as_flattened().to_vec()) });
    assert_eq!(arrays["is_valid"].data, NpyData::Bool(vec![true; 5]));
    assert_eq!(arrays["object_id"].data, NpyData::I32(ids.to_vec()));
    let err = labels::write_flow_npz(Cursor::new(Vec::new()), &flow, Some(&[true; 4]), None).unwrap_err();
    assert_eq!(err.to_string(), "inconsistent input: 4 validity mask entries for 5 points");
}

#[cfg(feature = "av2")]
mod av2 {
    use arrow_array::{Array, BooleanArray, Float32Array, Int32Array};
    use arrow_schema::DataType;

    use super::*;

    fn read_feather(bytes: &[u8]) -> arrow_array::RecordBatch {
        let reader = arrow_ipc::reader::FileReader::try_new(Cursor::new(bytes.to_vec()), None).unwrap();
        let batches: Vec<_> = reader.map(|b| b.unwrap()).collect();
        assert_eq!(batches.len(), 1);
        batches.into_iter().next().unwrap()
    }

    #[test]
    fn av2_zip_holds_one_feather_per_frame_with_flow_and_validity() {
        let flows = vec![sample_points(), vec![], vec![[0.5, -0.5, 0.25], [1.0, 2.0, 3.0]]];
        let valid = vec![vec![true, false, true, true, false], vec![], vec![false, true]];
        let ids = vec![vec![-1, 4, 4, -1, 0], vec![], vec![7, -1], vec![1]];
        let bytes = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, Some(&valid), Some(&ids))
            .unwrap()
            .into_inner();
        let entries = unzip(&bytes);
        let names: Vec<&str> = entries.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["000000.feather", "000001.feather", "000002.feather"]);
        for (k, (_, data)) in entries.iter().enumerate() {
            // Feather v2 is an Arrow IPC file: magic at both ends.
            assert!(data.starts_with(b"ARROW1") && data.ends_with(b"ARROW1"));
            let batch = read_feather(data);
            let schema = batch.schema();
            let cols: Vec<(&str, &DataType)> =
                schema.fields().iter().map(|f| (f.name().as_str(), f.data_type())).collect();
            assert_eq!(
                cols,
                [
                    ("flow_tx_m", &DataType::Float32),
                    ("flow_ty_m", &DataType::Float32),
                    ("flow_tz_m", &DataType::Float32),
                    ("is_valid", &DataType::Boolean),
                    ("object_id", &DataType::Int32)
                ]
            );
            assert_eq!(batch.num_rows(), flows[k].len());
            for axis in 0..3 {
                let col = batch.column(axis).as_any().downcast_ref::<Float32Array>().unwrap();
                let want: Vec<f32> = flows[k].iter().map(|f| f[axis]).collect();
                assert_eq!(col.values().to_vec(), want);
                assert_eq!(col.null_count(), 0);
            }
            let v = batch.column(3).as_any().downcast_ref::<BooleanArray>().unwrap();
            assert_eq!(v.iter().map(|b| b.unwrap()).collect::<Vec<_>>(), valid[k]);
            let o = batch.column(4).as_any().downcast_ref::<Int32Array>().unwrap();
            assert_eq!(o.values().to_vec(), ids[k]);
        }
    }

    #[test]
    fn av2_labels_written_a_frame_at_a_time_are_the_all_at_once_zip_entry_by_entry() {
        let flows = vec![sample_points(), vec![], vec![[0.5, -0.5, 0.25], [1.0, 2.0, 3.0]]];
        let ids = vec![vec![-1, 4, 4, -1, 0], vec![], vec![7, -1], vec![1]];
        let all = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, None, Some(&ids)).unwrap().into_inner();
        let mut w = labels::LabelsAv2Writer::new(Cursor::new(Vec::new()));
        for (k, frame_ids) in ids.iter().enumerate() {
            w.frame(flows.get(k).map(Vec::as_slice), frame_ids).unwrap();
        }
        let streamed = unzip(&w.finish().unwrap().into_inner());
        assert_eq!(streamed, unzip(&all));
        // One entry per frame with a flow (the last frame's ids have no flow and no entry), each
        // frame k's own Feather file.
        assert_eq!(streamed.len(), 3);
        for (k, (name, data)) in streamed.iter().enumerate() {
            assert_eq!(name, &format!("{k:06}.feather"));
            assert_eq!(data, &labels::write_flow_feather(Vec::new(), &flows[k], None, Some(&ids[k])).unwrap());
        }
        // Object ids that do not match the frame's flow are refused, naming the frame.
        let mut w = labels::LabelsAv2Writer::new(Cursor::new(Vec::new()));
        w.frame(Some(&sample_points()), &[-1; 5]).unwrap();
        let err = w.frame(Some(&sample_points()), &[-1]).unwrap_err();
        assert_eq!(err.to_string(), "inconsistent input: frame 1: 1 object ids for 5 points");
    }

    #[test]
    fn av2_zip_without_masks_marks_every_point_valid() {
        let flows = vec![sample_points()];
        let bytes = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, None, None).unwrap().into_inner();
        let batch = read_feather(&unzip(&bytes)[0].1);
        let v = batch.column(3).as_any().downcast_ref::<BooleanArray>().unwrap();
        assert_eq!(v.true_count(), 5);
        let o = batch.column(4).as_any().downcast_ref::<Int32Array>().unwrap();
        assert!(o.values().iter().all(|&id| id == -1), "no objects: every point -1");
    }

    #[test]
    fn av2_zip_rejects_masks_that_do_not_match_the_flows() {
        let flows = vec![sample_points(), sample_points()];
        let one = vec![vec![true; 5]];
        let err = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, Some(&one), None).unwrap_err();
        assert_eq!(err.to_string(), "inconsistent input: 1 validity masks for 2 flow frames");
        let short = vec![vec![true; 5], vec![true; 4]];
        let err = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, Some(&short), None).unwrap_err();
        assert_eq!(err.to_string(), "inconsistent input: frame 1: validity mask has 4 entries for 5 points");
        let ids = vec![vec![-1; 5], vec![-1; 3]];
        let err = labels::write_labels_av2_zip(Cursor::new(Vec::new()), &flows, None, Some(&ids)).unwrap_err();
        assert_eq!(err.to_string(), "inconsistent input: frame 1: 3 object ids for 5 points");
    }
}

/// Feather v2 sweeps (Argoverse 2) and the AV2 log layout.
#[cfg(feature = "av2")]
mod feather_sweeps {
    use std::sync::Arc;

    use arrow_array::{ArrayRef, Float32Array, Float64Array, Int32Array, RecordBatch};
    use arrow_schema::{DataType, Field, Schema};

    use super::*;
    use crate::io::av2::{self, LogError};
    use crate::io::feather::{self, Values};

    /// Points spanning AV2's ranges: near, far (beyond 64 m, where float16 steps are 6.25 cm),
    /// negative, a value float16 holds exactly.
    fn sweep_points() -> Vec<Point> {
        vec![[0.0, 0.0, 0.0], [1.3, -2.71, -1.9], [-75.37, 12.125, 3.3], [99.9, -0.001, 0.5], [8.0, 16.0, -32.0]]
    }

    /// One uncompressed IPC file of `batches`, all of `schema`.
    fn ipc_file(schema: &Arc<Schema>, batches: &[RecordBatch]) -> Vec<u8> {
        let mut writer = arrow_ipc::writer::FileWriter::try_new(Vec::new(), schema).unwrap();
        for b in batches {
            writer.write(b).unwrap();
        }
        writer.finish().unwrap();
        writer.into_inner().unwrap()
    }

    /// A table of float columns `names`, one batch per entry of `rows` (each row's values in
    /// column order), float32 when `f32` is set, else float64.
    fn float_table(names: &[&str], rows: &[Vec<Vec<f64>>], f32: bool) -> Vec<u8> {
        let t = if f32 { DataType::Float32 } else { DataType::Float64 };
        let schema = Arc::new(Schema::new(names.iter().map(|n| Field::new(*n, t.clone(), false)).collect::<Vec<_>>()));
        let batches: Vec<RecordBatch> = rows
            .iter()
            .map(|batch| {
                let columns: Vec<ArrayRef> = (0..names.len())
                    .map(|c| -> ArrayRef {
                        let v = batch.iter().map(|r| r[c]);
                        if f32 {
                            Arc::new(Float32Array::from_iter_values(v.map(|x| x as f32)))
                        } else {
                            Arc::new(Float64Array::from_iter_values(v))
                        }
                    })
                    .collect();
                RecordBatch::try_new(schema.clone(), columns).unwrap()
            })
            .collect();
        ipc_file(&schema, &batches)
    }

    fn rows(points: &[Point]) -> Vec<Vec<f64>> {
        points.iter().map(|p| p.iter().map(|&c| c as f64).collect()).collect()
    }

    #[test]
    fn an_av2_sweep_reads_back_within_float16_rounding() {
        let points = sweep_points();
        let bytes = av2::write_sweep(Vec::new(), &points).unwrap();
        assert!(bytes.starts_with(b"ARROW1") && bytes.ends_with(b"ARROW1"));
        assert_eq!(detect_format(&bytes, None).unwrap(), Format::Feather);
        // The content decides, whatever the name.
        assert_eq!(detect_format(&bytes, Some("sweep.bin")).unwrap(), Format::Feather);
        let back = read_points(&bytes, None).unwrap();
        assert_eq!(back.len(), points.len());
        for (p, q) in points.iter().zip(&back) {
            for (a, b) in p.iter().zip(q) {
                // float16 keeps 11 significant bits: rounding moves a value by at most 2^-11 of it.
                assert!((a - b).abs() <= a.abs() * 2f32.powi(-11) + 1e-7, "{p:?} read back as {q:?}");
            }
        }
        assert_eq!(back[4], [8.0, 16.0, -32.0], "powers of two are exact in float16");
        assert_eq!(read_points(&bytes, Some("315966000000000000.feather")).unwrap(), back);
    }

    #[test]
    fn float32_and_float64_columns_in_several_batches_read_exactly() {
        let points = sample_points();
        let (a, b) = points.split_at(2);
        for f32 in [true, false] {
            // Extra columns around the coordinates are skipped, whatever their order.
            let bytes = float_table(&["t", "z", "x", "y"], &[rows_zxy(a), rows_zxy(b)], f32);
            assert_eq!(read_points(&bytes, None).unwrap(), points, "float32: {f32}");
        }
        let empty = float_table(&["x", "y", "z"], &[], true);
        assert_eq!(read_points(&empty, None).unwrap(), Vec::<Point>::new());
    }

    /// Rows of `t, z, x, y` for the table of the test above.
    fn rows_zxy(points: &[Point]) -> Vec<Vec<f64>> {
        points.iter().map(|p| vec![-1.0, p[2] as f64, p[0] as f64, p[1] as f64]).collect()
    }

    #[test]
    fn a_nan_or_infinite_coordinate_is_an_error_naming_the_point() {
        let mut r = rows(&sample_points());
        r[3][1] = f64::NAN;
        let bytes = float_table(&["x", "y", "z"], &[r.clone()], true);
        assert!(matches!(read_points(&bytes, None), Err(ReadError::NonFinite { index: 3 })));
        // Finite in float64, infinite as the f32 the fit uses.
        r[3][1] = 1e300;
        let bytes = float_table(&["x", "y", "z"], &[r], false);
        assert!(matches!(read_points(&bytes, None), Err(ReadError::NonFinite { index: 3 })));
    }

    #[test]
    fn a_missing_or_non_float_coordinate_column_is_a_clear_error() {
        let bytes = float_table(&["y", "z", "intensity"], &[rows(&sample_points())], true);
        assert_eq!(err_text(read_points(&bytes, None)), "Feather header: no column 'x' (columns: y, z, intensity)");
        let schema = Arc::new(Schema::new(vec![
            Field::new("x", DataType::Int32, false),
            Field::new("y", DataType::Float32, false),
            Field::new("z", DataType::Float32, false),
        ]));
        let batch = RecordBatch::try_new(
            schema.clone(),
            vec![
                Arc::new(Int32Array::from(vec![1])),
                Arc::new(Float32Array::from(vec![2.0])),
                Arc::new(Float32Array::from(vec![3.0])),
            ],
        )
        .unwrap();
        assert_eq!(
            err_text(read_points(&ipc_file(&schema, &[batch]), None)),
            "unsupported Feather: integer column 'x': x, y, z must be float16, float32 or float64"
        );
    }

    #[test]
    fn truncated_and_damaged_files_are_errors_not_panics() {
        let bytes = av2::write_sweep(Vec::new(), &sweep_points()).unwrap();
        // Every cut of the file (the footer, then the batch, is lost).
        for len in 0..bytes.len() {
            assert!(read_points(&bytes[..len], Some("a.feather")).is_err(), "a cut to {len} bytes was read");
        }
        let mut no_magic = bytes.clone();
        no_magic.truncate(bytes.len() - 1);
        assert_eq!(
            err_text(read_points(&no_magic, None)),
            "Feather data: no 'ARROW1' magic at the end: the file is truncated (or an IPC stream, not a file)"
        );
        assert!(err_text(read_points(b"FEA1 an old feather file", None)).contains("Feather v1"));
        // A name picks the reader for content without magic; the reader says what is wrong.
        assert_eq!(
            err_text(read_points(b"not arrow at all", Some("sweep.feather"))),
            "Feather header: no 'ARROW1' magic at the start: not an Arrow IPC / Feather v2 file"
        );
    }

    /// Offset in `file` of the body of its first record batch and the (offset, length) of the
    /// batch's buffers within that body, read with arrow's own flatbuffer accessors.
    fn first_batch_layout(file: &[u8]) -> (usize, Vec<(usize, usize)>) {
        let footer_len = i32::from_le_bytes(file[file.len() - 10..file.len() - 6].try_into().unwrap()) as usize;
        let end = file.len() - 10;
        let footer = arrow_ipc::root_as_footer(&file[end - footer_len..end]).unwrap();
        let block = footer.recordBatches().unwrap().get(0);
        let meta = &file[block.offset() as usize..][..block.metaDataLength() as usize];
        let message = arrow_ipc::root_as_message(&meta[8..]).unwrap();
        let batch = message.header_as_record_batch().unwrap();
        let buffers = batch.buffers().unwrap().iter().map(|b| (b.offset() as usize, b.length() as usize)).collect();
        (block.offset() as usize + block.metaDataLength() as usize, buffers)
    }

    #[test]
    fn a_compressed_buffer_declaring_more_than_lz4_can_hold_is_refused_before_allocating() {
        let mut bytes = av2::write_sweep(Vec::new(), &sweep_points()).unwrap();
        let (body, buffers) = first_batch_layout(&bytes);
        // Buffer 1 holds x's values: an LZ4 frame after its int64 uncompressed length.
        let (offset, len) = buffers[1];
        assert!(len > 8);
        let at = body + offset;
        bytes[at..at + 8].copy_from_slice(&(1i64 << 50).to_le_bytes());
        let text = err_text(read_points(&bytes, None));
        assert!(text.contains("declares 1125899906842624 bytes, more than"), "{text}");
        // A buffer reaching past the body.
        let mut bytes = av2::write_sweep(Vec::new(), &sweep_points()).unwrap();
        let text = err_text(read_points(&patch_first_buffer_length(&mut bytes, 1 << 40), None));
        assert!(text.contains("lies outside the"), "{text}");
    }

    /// `file` with the declared length of buffer 1 of its first batch set to `len`, found by
    /// its current value in the message (the flatbuffer stores it as a little-endian int64).
    fn patch_first_buffer_length(file: &mut [u8], len: i64) -> Vec<u8> {
        let (_, buffers) = first_batch_layout(file);
        let (offset, old) = buffers[1];
        let mut pattern = (offset as i64).to_le_bytes().to_vec();
        pattern.extend_from_slice(&(old as i64).to_le_bytes());
        let at = file.windows(16).position(|w| w == pattern.as_slice()).expect("the buffer entry");
        file[at + 8..at + 16].copy_from_slice(&len.to_le_bytes());
        file.to_vec()
    }

    #[test]
    fn a_compressed_buffer_shorter_than_its_length_prefix_is_an_error() {
        // Found by the fuzzer (a compressed buffer of fewer than 8 bytes inside the body made the
        // size check underflow); kept in its corpus too.
        let bytes = include_bytes!("../../fuzz/corpus/feather/regression-short-compressed-buffer");
        let err = read_points(bytes, Some("x.feather")).unwrap_err();
        assert!(err.to_string().contains("length prefix"), "{err}");
    }

    #[test]
    fn numeric_columns_read_as_floats_and_exact_integers() {
        let poses = [[1.0, 0.0, 0.0, 5.0, 0.0, 1.0, 0.0, -2.0, 0.0, 0.0, 1.0, 0.25, 0.0, 0.0, 0.0, 1.0]];
        let timestamps_ns = [315_966_265_659_927_001i64];
        let bytes = av2::write_city_poses(Vec::new(), &timestamps_ns, &poses).unwrap();
        let columns = feather::read_columns(&bytes, &["timestamp_ns", "tx_m", "qw"]).unwrap();
        // An odd nanosecond count above 2^53: exact only as an integer.
        assert_eq!(columns, [Values::Int(timestamps_ns.to_vec()), Values::Float(vec![5.0]), Values::Float(vec![1.0])]);
        let back = av2::read_city_poses(&bytes, Path::new("p.feather")).unwrap();
        assert_eq!(back.len(), 1);
        let m = back[&timestamps_ns[0]];
        for (a, b) in m.iter().zip(&poses[0]) {
            assert!((a - b).abs() < 1e-12, "{m:?}");
        }
    }

    /// A log directory with sweeps at `timestamps_ns` and poses at `pose_times_ns` (a yaw of
    /// 0.1 rad per pose, 1 m along x per pose).
    fn write_log(dir: &Path, timestamps_ns: &[i64], pose_times_ns: &[i64]) {
        std::fs::create_dir_all(dir.join(av2::LIDAR_DIR)).unwrap();
        for &t in timestamps_ns {
            let bytes = av2::write_sweep(Vec::new(), &sample_points()).unwrap();
            std::fs::write(dir.join(av2::LIDAR_DIR).join(format!("{t}.feather")), bytes).unwrap();
        }
        let poses: Vec<[f64; 16]> = (0..pose_times_ns.len())
            .map(|k| {
                let (s, c) = (0.1 * k as f64).sin_cos();
                [c, -s, 0.0, k as f64, s, c, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
            })
            .collect();
        std::fs::write(dir.join(av2::POSES_FILE), av2::write_city_poses(Vec::new(), pose_times_ns, &poses).unwrap())
            .unwrap();
    }

    #[test]
    fn a_log_lists_sweeps_by_timestamp_with_their_poses() {
        let dir = tempfile::tempdir().unwrap();
        // 9 < 10 as numbers though "10" < "9" as names; poses in another order, one extra.
        write_log(dir.path(), &[10, 9, 1_000_000_000], &[1_000_000_000, 10, 9, 11]);
        let log = av2::read_log(dir.path()).unwrap();
        assert_eq!(log.timestamps_ns, [9, 10, 1_000_000_000]);
        assert!(log.sweep_paths[0].ends_with("9.feather"));
        let times_s = log.timestamps_s();
        assert_eq!(times_s[..2], [0.0, 1e-9]);
        assert!((times_s[2] - 0.999_999_991).abs() < 1e-15, "{times_s:?}");
        // The pose of timestamp 9 is the third row (k = 2): 2 m along x.
        assert_eq!(log.poses[0][3], 2.0);
        assert_eq!(log.poses[2][3], 0.0);
    }

    #[test]
    fn a_sweep_without_a_pose_or_a_bad_name_is_a_clear_error() {
        let dir = tempfile::tempdir().unwrap();
        write_log(dir.path(), &[100, 200], &[100]);
        let err = av2::read_log(dir.path()).unwrap_err();
        assert!(matches!(err, LogError::MissingPose { timestamp_ns: 200, .. }), "{err}");
        assert!(err.to_string().starts_with("sweep 200.feather has no pose of that timestamp in"), "{err}");
        std::fs::write(dir.path().join(av2::LIDAR_DIR).join("latest.feather"), b"").unwrap();
        assert!(matches!(av2::read_log(dir.path()).unwrap_err(), LogError::BadSweepName(_)));
        let empty = tempfile::tempdir().unwrap();
        assert!(matches!(av2::read_log(empty.path()).unwrap_err(), LogError::List { .. }));
    }
}

/// Without Arrow, a Feather upload is recognised and refused by name, not taken for KITTI.
#[cfg(not(feature = "av2"))]
#[test]
fn without_the_av2_feature_a_feather_file_is_a_clear_error() {
    let bytes = b"ARROW1\0\0 any body ARROW1";
    assert_eq!(detect_format(bytes, Some("a.bin")).unwrap(), Format::Feather);
    assert_eq!(
        err_text(read_points(bytes, None)),
        "unsupported Feather: this build has no Arrow support: rebuild with the `av2` cargo feature (on by default)"
    );
}

// ---------- never panic ----------

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn read_points_never_panics_on_arbitrary_bytes(
        bytes in proptest::collection::vec(any::<u8>(), 0..1024),
        hint in proptest::option::of("[a-z]{0,3}\\.(ply|pcd|bin|npy|txt)"),
    ) {
        let _ = read_points(&bytes, hint.as_deref());
    }

    #[test]
    fn read_points_never_panics_on_damaged_good_files(
        which in 0usize..8,
        cut in any::<prop::sample::Index>(),
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6),
    ) {
        let (name, mut bytes) = all_good_fixtures().swap_remove(which);
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        bytes.truncate(cut.index(bytes.len() + 1));
        let _ = read_points(&bytes, Some(name));
        let _ = read_points(&bytes, None);
        let _ = npy::read_npy(&bytes);
    }

    #[cfg(feature = "av2")]
    #[test]
    fn read_points_never_panics_on_damaged_feather_sweeps(
        cut in any::<prop::sample::Index>(),
        flips in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
    ) {
        let mut bytes = crate::io::av2::write_sweep(Vec::new(), &sample_points()).unwrap();
        for (at, value) in flips {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        bytes.truncate(cut.index(bytes.len() + 1));
        let _ = read_points(&bytes, Some("a.feather"));
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn every_format_round_trips_arbitrary_finite_points(
        points in proptest::collection::vec(proptest::array::uniform3(-1.0e4f32..1.0e4), 0..40),
    ) {
        // Rust prints the shortest decimal that parses back to the same f32, so the ascii
        // formats are exact too.
        let files = [
            ply_ascii(&points),
            ply_binary_double(&points),
            ply_binary_vertex_list(&points),
            pcd_ascii(&points),
            pcd_binary_f64(&points),
            npy_f32_n4(&points),
            npy_f64_n4(&points),
        ];
        for bytes in &files {
            prop_assert_eq!(&read_points(bytes, None).unwrap(), &points);
        }
        prop_assert_eq!(&read_points(&kitti_bin(&points), Some("x.bin")).unwrap(), &points);
    }

    #[test]
    fn npy_round_trips_any_shape_bit_exactly(
        shape in proptest::collection::vec(0usize..5, 0..4),
        seed_bits in proptest::collection::vec(any::<u32>(), 64),
    ) {
        let n: usize = shape.iter().product();
        // Arbitrary bit patterns, NaNs included: the array reader does not judge values.
        let data: Vec<f32> = (0..n).map(|i| f32::from_bits(seed_bits[i % 64].rotate_left(i as u32))).collect();
        let bytes = write(|b| npy::write_npy_f32(b, &shape, &data));
        let arr = npy::read_npy(&bytes).unwrap();
        prop_assert_eq!(&arr.shape, &shape);
        let NpyData::F32(got) = arr.data else { panic!("dtype changed") };
        prop_assert_eq!(got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), data.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
    }
}
