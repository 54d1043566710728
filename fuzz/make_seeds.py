#!/usr/bin/env python3
"""Writes the hand-made seed files of fuzz/corpus/<target>/ (valid and broken examples of each
format). The committed corpus is these seeds after the long runs and `cargo fuzz cmin`; run this
again only to start a corpus afresh: python3 fuzz/make_seeds.py

corpus/feather/ (and read_points/sweep_lz4_f16, read_points/feather_named_garbage) is not made
here: Python has no Arrow writer on this machine. Those seeds were written by mbnt's own writers:
io::av2::write_sweep of P below (LZ4, float16), the same cut by 7 bytes, with P[2].y = NaN, of no
points; io::av2::write_city_poses of two identity poses (no x, y, z); io::labels::
write_flow_feather of P (uncompressed float32); for read_points, selector byte 0 (no name) before
the sweep and 5 ("a.feather") before b"not arrow"."""
import os, struct
root = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'corpus')
P = [(0.0, 0.0, 0.0), (1.5, -2.25, 0.0), (-3.0, 4.0, 0.0), (10.125, 0.5, 1.75)]
def put(target, name, data):
    d = os.path.join(root, target); os.makedirs(d, exist_ok=True)
    if isinstance(data, str): data = data.encode()
    open(os.path.join(d, name), 'wb').write(data)
f32 = lambda *v: struct.pack('<%df' % len(v), *v)
f64 = lambda *v: struct.pack('<%dd' % len(v), *v)
ply = {}
s = "ply\nformat ascii 1.0\ncomment c\nelement camera 1\nproperty float fx\nproperty list uchar int ids\n"
s += "element vertex %d\nproperty uchar intensity\nproperty float x\nproperty float y\nproperty list uchar float extra\nproperty float z\nproperty double nx\n" % len(P)
s += "element face 1\nproperty list uchar int vertex_indices\nend_header\n500.0 3 1 2 3\n"
for i, p in enumerate(P): s += "%d %r %r 2 0.5 0.25 %r -1.0\n" % (i, p[0], p[1], p[2])
s += "3 0 1 2\n"
ply['ascii.ply'] = s.encode()
b = ("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\nend_header\n" % len(P)).encode()
ply['bin_f32.ply'] = b + b''.join(f32(*p) for p in P)
b = ("ply\r\nformat binary_little_endian 1.0\r\nelement sensor 1\r\nproperty short id\r\nproperty list uchar uint beams\r\nelement vertex %d\r\nproperty double x\r\nproperty uint ring\r\nproperty list uchar ushort tags\r\nproperty double y\r\nproperty double z\r\nend_header\r\n" % len(P)).encode()
b += struct.pack('<hB2I', 1, 2, 7, 8)
for i, p in enumerate(P): b += f64(p[0]) + struct.pack('<IBH', i, 1, 9) + f64(p[1], p[2])
ply['bin_f64_lists.ply'] = b
ply['truncated.ply'] = ply['bin_f32.ply'][:-5]
ply['nan.ply'] = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 nan 2\n".encode()
ply['big_endian.ply'] = b"ply\nformat binary_big_endian 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
for n, d in ply.items(): put('ply', n, d)
pcd = {}
s = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity hist\nSIZE 4 4 4 4 2\nTYPE F F F F U\nCOUNT 1 1 1 1 2\nWIDTH %d\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS %d\nDATA ascii\n" % (len(P), len(P))
for p in P: s += "%r %r %r 0.5 3 4\n" % p
pcd['ascii.pcd'] = s.encode()
b = ("VERSION .7\nFIELDS t x y z intensity _\nSIZE 4 8 8 8 4 1\nTYPE U F F F F U\nCOUNT 1 1 1 1 1 3\nWIDTH %d\nHEIGHT 1\nDATA binary\n" % len(P)).encode()
for i, p in enumerate(P): b += struct.pack('<I', i) + f64(*p) + f32(0.75) + bytes([1, 2, 3])
pcd['bin_f64.pcd'] = b
b = ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n").encode()
pcd['organised.pcd'] = b + b''.join(f32(*p) for p in P)
pcd['compressed.pcd'] = b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n\x00\x00"
for n, d in pcd.items(): put('pcd', n, d)
kitti = {'four.bin': b''.join(f32(*p, 0.3) for p in P), 'empty.bin': b'', 'ragged.bin': f32(1, 2, 3, 4, 5),
         'inf.bin': f32(1, float('inf'), 3, 0.1)}
for n, d in kitti.items(): put('kitti_bin', n, d)
# read_points: the first byte picks the file name (see HINTS in the target).
for i, (n, d) in enumerate(list(ply.items())[:2] + list(pcd.items())[:2] + [('four.bin', kitti['four.bin'])]):
    put('read_points', n, bytes([0]) + d)
put('read_points', 'kitti_named.bin', bytes([3]) + kitti['four.bin'])
put('read_points', 'ply_named_garbage', bytes([1]) + b'not a ply')
meta = {'full.json': '{"name": "drive 1", "timestamps": [0.0, 0.1, 0.2], "poses": [[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]]}',
        'empty.json': '{}', 'unknown.json': '{"name": "x", "frames": []}', 'nan.json': '{"timestamps": [NaN]}',
        'short_pose.json': '{"poses": [[1, 2, 3]]}', 'null.json': '{"name": null, "timestamps": [1e308, -0.0, 5e-324]}'}
for n, d in meta.items(): put('sequence_meta', n, d)
params = {'ints.json': '{"iterations": 100, "seed": 3, "hidden_width": 6.0}', 'mode.json': '{"mode": "faithful", "learning_rate": 0.001}',
          'null.json': '{"moving_bodies": null}', 'bad.json': '{"iterations": 1e30, "bogus": true}', 'array.json': '[1, 2]',
          'odometry.json': '{"odometry": "auto", "sample_points": 0, "validation_patience": 8.0}'}
for i, (n, d) in enumerate(params.items()): put('job_params', n, bytes([i]) + d.encode())
import zipfile, io
def npy(descr, shape, payload, fortran=False, version=1):
    shp = '(' + ''.join('%d, ' % d for d in shape)[:-2] + (',)' if len(shape) == 1 else ')') if shape else '()'
    h = "{'descr': '%s', 'fortran_order': %s, 'shape': %s, }" % (descr, 'True' if fortran else 'False', shp)
    pre = 10 if version == 1 else 12
    h += ' ' * ((64 - (pre + len(h) + 1) % 64) % 64) + '\n'
    lenf = struct.pack('<H', len(h)) if version == 1 else struct.pack('<I', len(h))
    return b'\x93NUMPY' + bytes([version, 0]) + lenf + h.encode() + payload
pts32 = b''.join(f32(*p) for p in P)
arr = {
    'points_f32.npy': npy('<f4', (4, 3), pts32),
    'points_f64_4col_v2.npy': npy('<f8', (2, 4), f64(1, 2, 3, 4, 5, 6, 7, 8), version=2),
    'fortran_i32.npy': npy('<i4', (2, 3), struct.pack('<6i', 1, 2, 3, 4, 5, 6), fortran=True),
    'i64_vec.npy': npy('<i8', (3,), struct.pack('<3q', -1, 0, 7)),
    'u8_scalar.npy': npy('|u1', (), b'\x05'),
    'bool.npy': npy('|b1', (2, 2), b'\x00\x01\x01\x00'),
    'big_endian.npy': npy('>f4', (1, 3), f32(1, 2, 3)),
    'truncated.npy': npy('<f4', (4, 3), pts32[:-1]),
    'structured.npy': b"\x93NUMPY\x01\x00" + struct.pack('<H', 54) + b"{'descr': [('x', '<f4')], 'fortran_order': False, 'shape': (1,), }\n"[:54],
}
for n, d in arr.items(): put('npy', n, d)
def npz(entries, method=zipfile.ZIP_DEFLATED):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, 'w', method) as z:
        for name, data in entries: z.writestr(name, data)
    return buf.getvalue()
put('npz', 'two.npz', npz([('pc.npy', arr['points_f32.npy']), ('idx.npy', arr['i64_vec.npy'])]))
put('npz', 'stored.npz', npz([('b.npy', arr['bool.npy'])], zipfile.ZIP_STORED))
put('npz', 'not_npy.npz', npz([('readme.txt', b'hello')]))
put('npz', 'bad_array.npz', npz([('t.npy', arr['truncated.npy'])]))
put('npz', 'empty.npz', npz([]))
# flow pair: pc1 with a NaN padding row, two scored points, est_flow for them.
nan = float('nan')
pc1 = [(0, 0, 0), (1, 2, 3), (nan, nan, nan), (4, 5, 6)]
pc2 = [(0.1, 0, 0), (1.1, 2, 3), (nan, nan, nan)]
flat = lambda rows: b''.join(f32(*r) for r in rows)
def pair(valid_idx, with_est=True, drop=None):
    e = [('pc1.npy', npy('<f4', (4, 3), flat(pc1))), ('pc2.npy', npy('<f4', (3, 3), flat(pc2))),
         ('gt_flow_0_1.npy', npy('<f4', (4, 3), flat([(0.1, 0, 0)] * 4))),
         ('pc1_flows_valid_idx.npy', npy('<i8', (len(valid_idx),), struct.pack('<%dq' % len(valid_idx), *valid_idx))),
         ('pc1_classes.npy', npy('<f4', (4,), f32(-1, 1, -1, 2))), ('ground1.npy', npy('<f4', (4,), f32(1, 0, 0, 0))),
         ('ground2.npy', npy('<f4', (3,), f32(1, 0, 0)))]
    if with_est: e.append(('est_flow.npy', npy('<f4', (len(valid_idx), 3), flat([(0.1, 0, 0)] * len(valid_idx)))))
    return npz([x for x in e if x[0] != drop])
put('flow_pair', 'pair.npz', pair([1, 3]))
put('flow_pair', 'pair_no_est.npz', pair([0], with_est=False))
put('flow_pair', 'index_on_padding.npz', pair([2]))
put('flow_pair', 'missing_ground2.npz', pair([1], drop='ground2.npy'))
