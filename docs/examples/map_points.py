#!/usr/bin/env python3
"""Map section pixels to atlas pixels and CCFv3 micrometres from a slicestation RESULT.json and
its field TIFF, with the Python standard library only (docs/results.md, "The mapping, exactly").

    map_points.py RESULT.json              re-map the result's own points, print the largest
                                           difference from the station's (atlas px)
    map_points.py RESULT.json X Y [X Y...] print atlas x, y and CCF x, y, z (um) for each pixel

The field TIFF is what slicestation writes: float32, two samples (dx, dy), deflate, floating-point
predictor (3), strips. With numpy and tifffile installed, tifffile.imread() reads it in one line.
"""
import json
import os
import struct
import sys
import zlib


def read_field(path):
    b = open(path, "rb").read()
    e = "<" if b[:2] == b"II" else ">"
    off = struct.unpack(e + "I", b[4:8])[0]
    tags = {}
    for i in range(struct.unpack(e + "H", b[off:off + 2])[0]):
        t, typ, cnt, val = struct.unpack(e + "HHII", b[off + 2 + 12 * i:off + 14 + 12 * i])
        size = {3: 2, 4: 4}.get(typ, 1)
        if cnt * size > 4:
            tags[t] = struct.unpack(e + ("H" if typ == 3 else "I") * cnt, b[val:val + cnt * size])
        else:
            tags[t] = (val & 0xFFFF,) if typ == 3 and e == "<" else (val,)
    w, h, spp = tags[256][0], tags[257][0], tags[277][0]
    data = b"".join(zlib.decompress(b[o:o + c]) if tags[259][0] in (8, 32946) else b[o:o + c]
                    for o, c in zip(tags[273], tags[279]))
    if tags.get(317, (1,))[0] == 3:  # floating-point predictor: byte planes, differenced
        n = w * spp
        out = bytearray()
        for y in range(h):
            row = bytearray(data[y * n * 4:(y + 1) * n * 4])
            for i in range(spp, n * 4):
                row[i] = (row[i] + row[i - spp]) & 255
            for i in range(n):
                out += bytes(row[i + k * n] for k in range(4))[::-1]
        data, e = bytes(out), "<"
    vals = struct.unpack(e + "%df" % (w * h * spp), data[:w * h * spp * 4])
    return w, h, spp, vals


class Mapping:
    def __init__(self, result_path):
        self.r = json.load(open(result_path))
        m = self.r["mapping"]
        self.cols, self.rows, self.spp, self.f = read_field(
            os.path.join(os.path.dirname(result_path) or ".", m["field"]))
        self.a = m["affine_atlas_from_working"]
        self.s = m["working_scale"]
        self.cell = m["field_node_spacing_working_px"]

    def atlas_px(self, x, y):
        s, a, cols, rows = self.s, self.a, self.cols, self.rows
        w = ((x + 0.5) * s - 0.5, (y + 0.5) * s - 0.5)
        p = [a[i][0] * w[0] + a[i][1] * w[1] + a[i][2] for i in range(2)]
        gx = min(max(w[0] / self.cell, 0), cols - 1)
        gy = min(max(w[1] / self.cell, 0), rows - 1)
        x0, y0 = min(int(gx), max(cols - 2, 0)), min(int(gy), max(rows - 2, 0))
        x1, y1 = min(x0 + 1, cols - 1), min(y0 + 1, rows - 1)
        fx, fy = gx - x0, gy - y0
        f = lambda yy, xx, k: self.f[(yy * cols + xx) * self.spp + k]
        return [p[k] + (1 - fy) * ((1 - fx) * f(y0, x0, k) + fx * f(y0, x1, k))
                + fy * ((1 - fx) * f(y1, x0, k) + fx * f(y1, x1, k)) for k in range(2)]

    def ccf_um(self, x, y):
        st = self.r["atlas"]["stack"]
        ax, ay = self.atlas_px(x, y)
        return [st["origin_um"][i] + ax * st["column_um"][i] + ay * st["row_um"][i]
                for i in range(3)]


def main():
    m = Mapping(sys.argv[1])
    if len(sys.argv) == 2:
        worst = 0.0
        for p in m.r["points"]:
            a = m.atlas_px(p["x"], p["y"])
            worst = max(worst, abs(a[0] - p["atlas_x"]), abs(a[1] - p["atlas_y"]))
        print("points %d max_difference_atlas_px %.3g" % (len(m.r["points"]), worst))
        return
    xy = [float(v) for v in sys.argv[2:]]
    for x, y in zip(xy[0::2], xy[1::2]):
        print(x, y, *["%.3f" % v for v in m.atlas_px(x, y) + m.ccf_um(x, y)])


if __name__ == "__main__":
    main()
