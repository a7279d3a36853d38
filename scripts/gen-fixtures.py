#!/usr/bin/env python3
"""Writes the mesh-reader test fixtures in server/tests/fixtures/.

The fixtures are written by `meshio` (pip install meshio), so that they come from a
different code path than the Rust readers in import/src/. The variants
meshio cannot write (appended VTK XML data, legacy SCALARS sections, non-contiguous gmsh
node tags, METADATA blocks, broken files) are written below with plain Python.

Every valid fixture holds the same small mesh: the box [0.1,0.8]x[0.2,0.9]x[0.3,1.0] split
into 6 tets around its main diagonal, plus a 7th tet on an apex above the top face
(9 points, 7 tets), with the point fields

    temperature = x + 2*y + 3*z
    pressure    = 101.325 * (1 + x - z)
    velocity    = (x, y, z)            (3 components: the readers skip it)

server/tests/mesh_io.rs recomputes these with the same f64 operations, so binary f64
variants compare exactly. The "mixed" fixtures add 2 triangles, 3 lines and 1 vertex
around the tets (6 ignored cells).

write_import_fixtures() adds the files of the import tests (server/tests/import_*.rs):
gmsh 1.0 and Medit versions of the cube, cell arrays (density = tet index + 1, flow =
(i, 2i, 0)), quadratic tets, a mesh of 2 hexahedra, a wedge and a pyramid ("volcells"),
a bare mesh, a surface-only mesh, CRLF and blank lines, and more broken files.

Usage (meshio 5.3 writes numpy-2 scalars as "np.float64(...)" in ascii gmsh data, so
use numpy < 2):

    python3 -m venv /tmp/fixenv && /tmp/fixenv/bin/pip install meshio "numpy<2"
    /tmp/fixenv/bin/python scripts/gen-fixtures.py

It rewrites the whole folder; the output is deterministic for a given meshio version.
"""

import base64
import pathlib
import shutil
import struct
import zlib

import meshio
import numpy as np

OUT = pathlib.Path(__file__).resolve().parent.parent / "server" / "tests" / "fixtures"

XS = (0.1, 0.8)
YS = (0.2, 0.9)
ZS = (0.3, 1.0)
# Corner index = i + 2*j + 4*k for x = XS[i], y = YS[j], z = ZS[k]; then the apex.
POINTS = [(XS[i], YS[j], ZS[k]) for k in range(2) for j in range(2) for i in range(2)]
POINTS.append((0.45, 0.55, 1.4))
TETS = [
    [0, 1, 3, 7],
    [0, 1, 5, 7],
    [0, 2, 3, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 4, 6, 7],
    [4, 5, 7, 8],
]
TRIANGLES = [[0, 1, 3], [0, 3, 2]]
LINES = [[0, 1], [1, 3], [3, 7]]
VERTICES = [[8]]


def temperature(p):
    x, y, z = p
    return x + 2.0 * y + 3.0 * z


def pressure(p):
    x, y, z = p
    return 101.325 * (1.0 + x - z)


TEMPERATURE = [temperature(p) for p in POINTS]
PRESSURE = [pressure(p) for p in POINTS]

# VTK cell type numbers.
VTK_VERTEX, VTK_LINE, VTK_TRIANGLE, VTK_TETRA = 1, 3, 5, 10


def out(name):
    return OUT / name


def point_data(dtype=np.float64):
    pts = np.array(POINTS, dtype=np.float64)
    return {
        "temperature": np.array(TEMPERATURE, dtype=np.float64).astype(dtype),
        "pressure": np.array(PRESSURE, dtype=np.float64).astype(dtype),
        "velocity": pts.astype(dtype),
    }


def cube_mesh(point_dtype=np.float64, index_dtype=np.int64):
    return meshio.Mesh(
        np.array(POINTS, dtype=np.float64).astype(point_dtype),
        [("tetra", np.array(TETS, dtype=index_dtype))],
        point_data=point_data(point_dtype),
    )


def mixed_mesh():
    return meshio.Mesh(
        np.array(POINTS, dtype=np.float64),
        [
            ("triangle", np.array(TRIANGLES, dtype=np.int64)),
            ("tetra", np.array(TETS, dtype=np.int64)),
            ("line", np.array(LINES, dtype=np.int64)),
            ("vertex", np.array(VERTICES, dtype=np.int64)),
        ],
        point_data=point_data(),
    )


def mixed_mesh_gmsh():
    mesh = mixed_mesh()
    # gmsh 4.1 needs entity information for more than one cell block.
    mesh.point_data["gmsh:dim_tags"] = np.array([[3, 1]] * len(POINTS))
    mesh.cell_data["gmsh:physical"] = [np.full(len(c.data), 1) for c in mesh.cells]
    mesh.cell_data["gmsh:geometrical"] = [np.full(len(c.data), 1) for c in mesh.cells]
    return mesh


# ---------------------------------------------------------------------------------------
# Written by meshio.


def write_meshio():
    meshio.vtu.write(out("cube_ascii.vtu"), cube_mesh(), binary=False)
    meshio.vtu.write(out("cube_binary.vtu"), cube_mesh(), binary=True, compression=None)
    meshio.vtu.write(out("cube_binary_zlib.vtu"), cube_mesh(), binary=True)
    meshio.vtu.write(
        out("cube_f32_i32_zlib_h64.vtu"),
        cube_mesh(np.float32, np.int32),
        binary=True,
        compression="zlib",
        header_type="UInt64",
    )
    meshio.vtu.write(out("mixed.vtu"), mixed_mesh(), binary=True)

    for version in ("4.2", "5.1"):
        tag = version.replace(".", "")
        for binary in (False, True):
            kind = "binary" if binary else "ascii"
            meshio.vtk.write(
                out(f"cube_{tag}_{kind}.vtk"), cube_mesh(), fmt_version=version, binary=binary
            )
    meshio.vtk.write(
        out("cube_42_f32_binary.vtk"),
        cube_mesh(np.float32, np.int32),
        fmt_version="4.2",
        binary=True,
    )
    meshio.vtk.write(out("mixed_51.vtk"), mixed_mesh(), fmt_version="5.1", binary=True)
    meshio.vtk.write(out("mixed_42_ascii.vtk"), mixed_mesh(), fmt_version="4.2", binary=False)

    for version in ("2.2", "4.1"):
        tag = version.replace(".", "")
        for binary in (False, True):
            kind = "binary" if binary else "ascii"
            meshio.gmsh.write(
                out(f"cube_{tag}_{kind}.msh"), cube_mesh(), fmt_version=version, binary=binary
            )
        meshio.gmsh.write(
            out(f"mixed_{tag}_ascii.msh"), mixed_mesh_gmsh(), fmt_version=version, binary=False
        )
        meshio.gmsh.write(
            out(f"mixed_{tag}_binary.msh"), mixed_mesh_gmsh(), fmt_version=version, binary=True
        )

    # A larger grid, so that zlib-compressed arrays span several 32 KiB blocks.
    n = 9
    coords = np.linspace(0.0, 1.0, n)
    grid_points = np.array([(x, y, z) for z in coords for y in coords for x in coords])

    def gid(i, j, k):
        return i + n * j + n * n * k

    grid_tets = []
    for k in range(n - 1):
        for j in range(n - 1):
            for i in range(n - 1):
                c = [gid(i + a, j + b, k + d) for d in (0, 1) for b in (0, 1) for a in (0, 1)]
                for t in TETS[:6]:
                    grid_tets.append([c[v] for v in t])
    gp = grid_points
    meshio.vtu.write(
        out("grid_zlib.vtu"),
        meshio.Mesh(
            gp,
            [("tetra", np.array(grid_tets, dtype=np.int64))],
            point_data={"temperature": gp[:, 0] + 2.0 * gp[:, 1] + 3.0 * gp[:, 2]},
        ),
        binary=True,
    )


# ---------------------------------------------------------------------------------------
# VTK XML with appended data (meshio only writes inline data).


def vtu_appended(name, encoding, compress, header_type="UInt32", byte_order="LittleEndian",
                 block_size=64, information_key=False):
    """Appended .vtu written the way VTK writes it: per array a header (the byte count,
    or [nblocks, block size, last block size, compressed sizes...]) then the data; with
    base64 the header and the data are encoded separately."""
    bo = "<" if byte_order == "LittleEndian" else ">"
    hfmt = {"UInt32": "I", "UInt64": "Q"}[header_type]

    def pack(fmt, values):
        return struct.pack(f"{bo}{len(values)}{fmt}", *values)

    def header(values):
        return pack(hfmt, values)

    def encode(raw):
        if compress:
            blocks = [raw[i:i + block_size] for i in range(0, len(raw), block_size)] or [b""]
            comp = [zlib.compress(b) for b in blocks]
            last = len(blocks[-1]) if len(blocks[-1]) != block_size else 0
            head = header([len(blocks), block_size, last] + [len(c) for c in comp])
            body = b"".join(comp)
        else:
            head = header([len(raw)])
            body = raw
        if encoding == "base64":
            return base64.b64encode(head) + base64.b64encode(body)
        return head + body

    flat_points = [c for p in POINTS for c in p]
    conn = [i for t in TETS for i in t]
    offsets = [4 * (i + 1) for i in range(len(TETS))]
    arrays = [
        ("Points", "Float64", 3, pack("d", flat_points)),
        ("connectivity", "Int64", 1, pack("q", conn)),
        ("offsets", "Int64", 1, pack("q", offsets)),
        ("types", "UInt8", 1, bytes([VTK_TETRA] * len(TETS))),
        ("temperature", "Float64", 1, pack("d", TEMPERATURE)),
        ("velocity", "Float32", 3, pack("f", flat_points)),
        ("pressure", "Float64", 1, pack("d", PRESSURE)),
        ("cellid", "Int32", 1, pack("i", list(range(len(TETS))))),
    ]
    appended = b""
    tags = {}
    for aname, atype, ncomp, raw in arrays:
        extra = ""
        info = ""
        if aname == "Points" and information_key:
            extra = ' RangeMin="0.3741657386773941" RangeMax="1.6911534525287764"'
            info = (
                '\n          <InformationKey name="L2_NORM_RANGE" location="vtkDataArray"'
                ' length="2">\n            <Value index="0">\n              0.37\n'
                '            </Value>\n          </InformationKey>\n        '
            )
        tags[aname] = (
            f'<DataArray type="{atype}" Name="{aname}" NumberOfComponents="{ncomp}"'
            f' format="appended"{extra} offset="{len(appended)}"'
            + (f">{info}</DataArray>" if info else "/>")
        )
        appended += encode(raw)
    compressor = ' compressor="vtkZLibDataCompressor"' if compress else ""
    xml = f"""<?xml version="1.0"?>
<VTKFile type="UnstructuredGrid" version="1.0" byte_order="{byte_order}" header_type="{header_type}"{compressor}>
  <!-- hand-written by scripts/gen-fixtures.py -->
  <UnstructuredGrid>
    <Piece NumberOfPoints="{len(POINTS)}" NumberOfCells="{len(TETS)}">
      <PointData Scalars="temperature">
        {tags["temperature"]}
        {tags["velocity"]}
        {tags["pressure"]}
      </PointData>
      <CellData>
        {tags["cellid"]}
      </CellData>
      <Points>
        {tags["Points"]}
      </Points>
      <Cells>
        {tags["connectivity"]}
        {tags["offsets"]}
        {tags["types"]}
      </Cells>
    </Piece>
  </UnstructuredGrid>
  <AppendedData encoding="{encoding}">
   _"""
    data = xml.encode() + appended + b"\n  </AppendedData>\n</VTKFile>\n"
    out(name).write_bytes(data)
    return data


def write_vtu_appended():
    vtu_appended("cube_appended_raw.vtu", "raw", False, information_key=True)
    vtu_appended("cube_appended_raw_zlib.vtu", "raw", True)
    vtu_appended("cube_appended_raw_be_h64.vtu", "raw", False, "UInt64", "BigEndian")
    vtu_appended("cube_appended_base64.vtu", "base64", False)
    vtu_appended("cube_appended_base64_zlib.vtu", "base64", True, "UInt64")


def write_vtu_two_pieces():
    """Two pieces: the first holds 2 extra points and a line between them, the second
    the cube mesh; cells use piece-local point indices, so the reader must shift the
    second piece's indices by 2."""
    def da(name, typ, values, ncomp=1):
        text = " ".join(repr(v) for v in values)
        return (f'<DataArray type="{typ}" Name="{name}" NumberOfComponents="{ncomp}"'
                f' format="ascii">{text}</DataArray>')

    def piece(lo, hi, tets):
        pts = POINTS[lo:hi]
        local = [[i - lo for i in t] for t in tets]
        return f"""    <Piece NumberOfPoints="{len(pts)}" NumberOfCells="{len(tets)}">
      <PointData>
        {da("temperature", "Float64", TEMPERATURE[lo:hi])}
        {da("pressure", "Float64", PRESSURE[lo:hi])}
      </PointData>
      <Points>
        {da("Points", "Float64", [c for p in pts for c in p], 3)}
      </Points>
      <Cells>
        {da("connectivity", "Int32", [i for t in local for i in t])}
        {da("offsets", "Int32", [4 * (i + 1) for i in range(len(tets))])}
        {da("types", "UInt8", [VTK_TETRA] * len(tets))}
      </Cells>
    </Piece>
"""
    extra = [(2.0, 2.0, 2.0), (3.0, 3.0, 3.0)]
    first = f"""    <Piece NumberOfPoints="2" NumberOfCells="1">
      <PointData>
        {da("temperature", "Float64", [temperature(p) for p in extra])}
        {da("pressure", "Float64", [pressure(p) for p in extra])}
      </PointData>
      <Points>
        {da("Points", "Float64", [c for p in extra for c in p], 3)}
      </Points>
      <Cells>
        {da("connectivity", "Int32", [0, 1])}
        {da("offsets", "Int32", [2])}
        {da("types", "UInt8", [VTK_LINE])}
      </Cells>
    </Piece>
"""
    xml = f"""<?xml version="1.0"?>
<VTKFile type="UnstructuredGrid" version="0.1" byte_order="LittleEndian">
  <UnstructuredGrid>
{first}{piece(0, len(POINTS), TETS)}  </UnstructuredGrid>
</VTKFile>
"""
    out("two_pieces.vtu").write_text(xml)


# ---------------------------------------------------------------------------------------
# Legacy VTK variants meshio does not write (it writes point data as FIELD arrays).


def write_legacy_scalars():
    lines = [
        "# vtk DataFile Version 3.0",
        "hand-written by gen-fixtures.py: SCALARS and VECTORS",
        "ASCII",
        "",
        "DATASET UNSTRUCTURED_GRID",
        f"POINTS {len(POINTS)} double",
    ]
    lines += [" ".join(repr(c) for c in p) for p in POINTS]
    lines.append(f"CELLS {len(TETS)} {5 * len(TETS)}")
    lines += ["4 " + " ".join(str(i) for i in t) for t in TETS]
    lines.append(f"CELL_TYPES {len(TETS)}")
    lines += [str(VTK_TETRA)] * len(TETS)
    lines.append(f"CELL_DATA {len(TETS)}")
    lines.append("SCALARS cellid int 1")
    lines.append("LOOKUP_TABLE default")
    lines += [str(i) for i in range(len(TETS))]
    lines.append(f"POINT_DATA {len(POINTS)}")
    lines.append("SCALARS temperature double 1")
    lines.append("LOOKUP_TABLE default")
    lines += [repr(v) for v in TEMPERATURE]
    lines.append("VECTORS velocity double")
    lines += [" ".join(repr(c) for c in p) for p in POINTS]
    lines.append("SCALARS pressure double")  # numComp omitted: defaults to 1
    lines.append("LOOKUP_TABLE my_table")
    lines += [repr(v) for v in PRESSURE]
    lines.append("LOOKUP_TABLE my_table 2")
    lines += ["0.0 0.0 0.0 1.0", "1.0 1.0 1.0 1.0"]
    out("cube_scalars_ascii.vtk").write_text("\n".join(lines) + "\n")

    # Binary: float points, SCALARS (float), FIELD arrays with a METADATA block.
    def be(fmt, values):
        return struct.pack(f">{len(values)}{fmt}", *values)

    b = b"# vtk DataFile Version 4.2\nhand-written by gen-fixtures.py\nBINARY\n"
    b += b"DATASET UNSTRUCTURED_GRID\n"
    b += f"POINTS {len(POINTS)} float\n".encode()
    b += be("f", [c for p in POINTS for c in p]) + b"\n"
    b += b"METADATA\nINFORMATION 0\n\n"
    b += f"CELLS {len(TETS)} {5 * len(TETS)}\n".encode()
    b += be("i", [v for t in TETS for v in [4] + t]) + b"\n"
    b += f"CELL_TYPES {len(TETS)}\n".encode()
    b += be("i", [VTK_TETRA] * len(TETS)) + b"\n"
    b += f"POINT_DATA {len(POINTS)}\n".encode()
    b += b"SCALARS temperature float 1\nLOOKUP_TABLE default\n"
    b += be("f", TEMPERATURE) + b"\n"
    b += b"FIELD FieldData 2\n"
    b += f"velocity 3 {len(POINTS)} float\n".encode()
    b += be("f", [c for p in POINTS for c in p]) + b"\n"
    b += f"pressure 1 {len(POINTS)} double\n".encode()
    b += be("d", PRESSURE) + b"\n"
    b += b"METADATA\nINFORMATION 1\nNAME L2_NORM_RANGE LOCATION vtkDataArray\nDATA 2 0 1\n\n"
    out("cube_scalars_binary.vtk").write_bytes(b)

    # 5.1 ascii with 32-bit OFFSETS/CONNECTIVITY and METADATA after the points.
    lines = [
        "# vtk DataFile Version 5.1",
        "hand-written by gen-fixtures.py: 5.1 with vtktypeint32 and METADATA",
        "ASCII",
        "DATASET UNSTRUCTURED_GRID",
        "FIELD FieldData 1",
        "TIME 1 1 double",
        "0.5",
        f"POINTS {len(POINTS)} double",
    ]
    lines += [" ".join(repr(c) for c in p) for p in POINTS]
    lines += ["METADATA", "INFORMATION 1", "NAME L2_NORM_RANGE LOCATION vtkDataArray",
              "DATA 2 0.37 1.69", ""]
    lines.append(f"CELLS {len(TETS) + 1} {4 * len(TETS)}")
    lines.append("OFFSETS vtktypeint32")
    lines.append(" ".join(str(4 * i) for i in range(len(TETS) + 1)))
    lines.append("CONNECTIVITY vtktypeint32")
    lines += [" ".join(str(i) for i in t) for t in TETS]
    lines.append(f"CELL_TYPES {len(TETS)}")
    lines += [str(VTK_TETRA)] * len(TETS)
    lines.append(f"POINT_DATA {len(POINTS)}")
    lines.append("FIELD FieldData 2")
    lines.append(f"temperature 1 {len(POINTS)} double")
    lines += [repr(v) for v in TEMPERATURE]
    lines += ["METADATA", "INFORMATION 0", ""]
    lines.append(f"pressure 1 {len(POINTS)} double")
    lines += [repr(v) for v in PRESSURE]
    out("cube_51_metadata.vtk").write_text("\n".join(lines) + "\n")


# ---------------------------------------------------------------------------------------
# gmsh with non-contiguous, unsorted node tags (meshio numbers nodes 1..n).

NODE_TAGS = [50, 12, 7, 31, 99, 100, 3, 64, 20]


def msh22_tags(binary):
    s = b"$MeshFormat\n" + (b"2.2 1 8\n" if binary else b"2.2 0 8\n")
    if binary:
        s += struct.pack("<i", 1) + b"\n"
    s += b"$EndMeshFormat\n"
    s += b'$PhysicalNames\n1\n3 1 "volume"\n$EndPhysicalNames\n'
    s += f"$Nodes\n{len(POINTS)}\n".encode()
    for tag, p in zip(NODE_TAGS, POINTS):
        if binary:
            s += struct.pack("<i3d", tag, *p)
        else:
            s += f"{tag} {p[0]!r} {p[1]!r} {p[2]!r}\n".encode()
    if binary:
        s += b"\n"
    s += b"$EndNodes\n"
    s += f"$Elements\n{len(TETS)}\n".encode()
    if binary:
        # Two element blocks of tets, 3 tags each (physical, elementary, partition).
        for lo, hi in ((0, 4), (4, len(TETS))):
            s += struct.pack("<3i", 4, hi - lo, 3)
            for e in range(lo, hi):
                s += struct.pack("<8i", 1000 + e, 1, 2, 0, *[NODE_TAGS[v] for v in TETS[e]])
        s += b"\n"
    else:
        for e, t in enumerate(TETS):
            s += f"{1000 + e} 4 2 1 2 {' '.join(str(NODE_TAGS[v]) for v in t)}\n".encode()
    s += b"$EndElements\n"
    s += msh_node_data("temperature", TEMPERATURE, binary, reverse=True)
    s += msh_node_data("velocity", [c for p in POINTS for c in p], binary, ncomp=3)
    s += msh_node_data("pressure", PRESSURE, binary)
    s += b"$Comments\nthis section is unknown to readers and skipped\n$EndComments\n"
    return s


def msh_node_data(name, values, binary, ncomp=1, reverse=False):
    """A $NodeData block; values are per point (index order), written with node tags,
    in reverse order when asked."""
    n = len(POINTS)
    s = b"$NodeData\n1\n" + f'"{name}"\n'.encode() + b"1\n0.0\n3\n0\n"
    s += f"{ncomp}\n{n}\n".encode()
    order = list(range(n))
    if reverse:
        order.reverse()
    for i in order:
        vals = values[i * ncomp:(i + 1) * ncomp]
        if binary:
            s += struct.pack(f"<i{ncomp}d", NODE_TAGS[i], *vals)
        else:
            s += (f"{NODE_TAGS[i]} " + " ".join(repr(v) for v in vals) + "\n").encode()
    if binary:
        s += b"\n"
    s += b"$EndNodeData\n"
    return s


def msh41_tags(binary):
    """gmsh 4.1 with $Entities, two node blocks (one parametric) and unsorted tags."""
    def size_t(*v):
        return struct.pack(f"<{len(v)}Q", *v)

    def i32(*v):
        return struct.pack(f"<{len(v)}i", *v)

    def f64(*v):
        return struct.pack(f"<{len(v)}d", *v)

    s = b"$MeshFormat\n" + (b"4.1 1 8\n" if binary else b"4.1 0 8\n")
    if binary:
        s += i32(1) + b"\n"
    s += b"$EndMeshFormat\n"
    # Entities: 1 point, 0 curves, 1 surface, 1 volume.
    if binary:
        ent = size_t(1, 0, 1, 1)
        ent += i32(1) + f64(0.1, 0.2, 0.3) + size_t(0)
        ent += i32(1) + f64(0.1, 0.2, 0.3, 0.8, 0.9, 0.3) + size_t(0) + size_t(0)
        ent += i32(1) + f64(0.1, 0.2, 0.3, 0.8, 0.9, 1.4) + size_t(1) + i32(7)
        ent += size_t(1) + i32(1)
        s += b"$Entities\n" + ent + b"\n$EndEntities\n"
    else:
        s += b"$Entities\n1 0 1 1\n1 0.1 0.2 0.3 0\n1 0.1 0.2 0.3 0.8 0.9 0.3 0 0\n"
        s += b"1 0.1 0.2 0.3 0.8 0.9 1.4 1 7 1 1\n$EndEntities\n"
    # Node blocks: the first 3 points on surface 1 (parametric, u v per node), the
    # rest in volume 1.
    blocks = [(2, 1, 1, list(range(3))), (3, 1, 0, list(range(3, len(POINTS))))]
    n = len(POINTS)
    if binary:
        s += b"$Nodes\n" + size_t(len(blocks), n, min(NODE_TAGS), max(NODE_TAGS))
        for dim, etag, param, idx in blocks:
            s += i32(dim, etag, param) + size_t(len(idx))
            s += size_t(*[NODE_TAGS[i] for i in idx])
            for i in idx:
                s += f64(*POINTS[i]) + (f64(0.25, 0.75) if param else b"")
        s += b"\n$EndNodes\n"
    else:
        s += f"$Nodes\n{len(blocks)} {n} {min(NODE_TAGS)} {max(NODE_TAGS)}\n".encode()
        for dim, etag, param, idx in blocks:
            s += f"{dim} {etag} {param} {len(idx)}\n".encode()
            s += b"".join(f"{NODE_TAGS[i]}\n".encode() for i in idx)
            for i in idx:
                p = POINTS[i]
                s += f"{p[0]!r} {p[1]!r} {p[2]!r}".encode()
                s += b" 0.25 0.75\n" if param else b"\n"
        s += b"$EndNodes\n"
    # Element blocks: a triangle on surface 1, then the tets split in two blocks.
    eblocks = [(2, 1, 2, [[0, 1, 2]]), (3, 1, 4, TETS[:3]), (3, 1, 4, TETS[3:])]
    ne = sum(len(b[3]) for b in eblocks)
    etag = 500
    if binary:
        s += b"$Elements\n" + size_t(len(eblocks), ne, etag, etag + ne - 1)
        for dim, ent, typ, elems in eblocks:
            s += i32(dim, ent, typ) + size_t(len(elems))
            for e in elems:
                s += size_t(etag, *[NODE_TAGS[v] for v in e])
                etag += 1
        s += b"\n$EndElements\n"
    else:
        s += f"$Elements\n{len(eblocks)} {ne} {etag} {etag + ne - 1}\n".encode()
        for dim, ent, typ, elems in eblocks:
            s += f"{dim} {ent} {typ} {len(elems)}\n".encode()
            for e in elems:
                s += f"{etag} {' '.join(str(NODE_TAGS[v]) for v in e)}\n".encode()
                etag += 1
        s += b"$EndElements\n"
    s += msh_node_data("pressure", PRESSURE, binary, reverse=True)
    s += msh_node_data("temperature", TEMPERATURE, binary)
    return s


def write_msh_tags():
    out("cube_22_tags_ascii.msh").write_bytes(msh22_tags(False))
    out("cube_22_tags_binary.msh").write_bytes(msh22_tags(True))
    out("cube_41_tags_ascii.msh").write_bytes(msh41_tags(False))
    out("cube_41_tags_binary.msh").write_bytes(msh41_tags(True))


# ---------------------------------------------------------------------------------------
# Broken files.


def cut(src, name, fraction):
    data = out(src).read_bytes()
    out(name).write_bytes(data[: int(len(data) * fraction)])


def cut_at(src, name, marker, extra):
    """Cuts `src` `extra` bytes after the first occurrence of `marker`."""
    data = out(src).read_bytes()
    pos = data.index(marker) + len(marker) + extra
    out(name).write_bytes(data[:pos])


def write_broken():
    cut("cube_binary_zlib.vtu", "truncated.vtu", 0.6)
    cut_at("cube_appended_raw.vtu", "truncated_appended.vtu", b"encoding=\"raw\">", 200)
    # Deterministic garbage (a linear congruential generator).
    x = 12345
    garbage = bytearray()
    for _ in range(3000):
        x = (1103515245 * x + 12345) % (1 << 31)
        garbage.append(x >> 23)
    out("garbage.vtu").write_bytes(bytes(garbage))
    cut_at("cube_22_ascii.msh", "truncated_ascii.msh", b"$Elements\n", 40)
    cut_at("cube_22_binary.msh", "truncated_binary.msh", b"$Nodes\n", 60)
    cut_at("cube_41_binary.msh", "truncated_41_binary.msh", b"$Elements\n", 50)

    # An element refers to node 99, which the $Nodes section does not define.
    text = out("cube_22_ascii.msh").read_text()
    head, elements = text.split("$Elements\n", 1)
    lines = elements.split("\n")
    fields = lines[3].split()
    fields[-1] = "99"
    lines[3] = " ".join(fields)
    out("node_out_of_range.msh").write_text(head + "$Elements\n" + "\n".join(lines))

    # Connectivity index 99 in a 9-point .vtu.
    text = out("cube_ascii.vtu").read_text()
    key = 'Name="connectivity" format="ascii">'
    pos = text.index(key) + len(key)
    first = text[pos:].split()[0]
    start = text.index(first, pos)
    text = text[:start] + "99" + text[start + len(first):]
    out("node_out_of_range.vtu").write_text(text)

    # Header counts that disagree with the data.
    text = out("cube_scalars_ascii.vtk").read_text()
    out("bad_point_count.vtk").write_text(text.replace(f"POINTS {len(POINTS)} double",
                                                       "POINTS 12 double"))
    out("bad_cell_types.vtk").write_text(text.replace(f"CELL_TYPES {len(TETS)}",
                                                      f"CELL_TYPES {len(TETS) + 2}"))
    out("bad_point_data_count.vtk").write_text(text.replace(f"POINT_DATA {len(POINTS)}",
                                                            "POINT_DATA 4"))
    # Counts far beyond the file size: must fail without allocating for them.
    data = out("cube_42_binary.vtk").read_bytes()
    out("huge_count.vtk").write_bytes(
        data.replace(f"POINTS {len(POINTS)} ".encode(), b"POINTS 4000000000 "))
    data = out("cube_22_binary.msh").read_bytes()
    out("huge_count.msh").write_bytes(
        data.replace(f"$Nodes\n{len(POINTS)}\n".encode(), b"$Nodes\n2000000000\n"))

    for ext in ("vtu", "vtk", "msh"):
        out(f"empty.{ext}").write_bytes(b"")


# ---------------------------------------------------------------------------------------
# Import of real-world files (issue 7): gmsh 1.0, Medit, cell data, higher-order and
# mixed volume cells, quirks and more broken files.

# Mixed volume cells: hex A = [0,1]^3, hex B = [1,2]x[0,1]^2 (sharing the face x=1), a
# wedge on A's top face (ridge along y at z=1.5), a pyramid on B's top face (apex at
# (1.5,0.5,1.5)). Point numbering deliberately not sorted by position.
VOL_POINTS = [
    (1, 0, 0), (0, 0, 0), (0, 1, 0), (1, 1, 0),      # 0-3: bottom of A (x=1 side first)
    (1, 0, 1), (0, 0, 1), (0, 1, 1), (1, 1, 1),      # 4-7: top of A
    (2, 0, 0), (2, 1, 0), (2, 0, 1), (2, 1, 1),      # 8-11: far side of B
    (0.5, 0, 1.5), (0.5, 1, 1.5), (1.5, 0.5, 1.5),   # 12-14: wedge ridge, pyramid apex
]
# VTK corner order (hex: bottom counter-clockwise seen from above, then top).
VOL_HEXES = [[1, 0, 3, 2, 5, 4, 7, 6], [0, 8, 9, 3, 4, 10, 11, 7]]
VOL_WEDGES = [[5, 4, 12, 6, 7, 13]]  # (0,1,2) at y=0, normal -y: away from (3,4,5)
VOL_PYRAMIDS = [[4, 10, 11, 7, 14]]
VOL_TRIANGLES = [[1, 0, 8]]


def write_import_fixtures():
    pts = np.array(VOL_POINTS, dtype=np.float64)
    height = pts[:, 2].copy()
    # meshio's wedge is gmsh's prism (its (0,1,2) turns towards (3,4,5)); meshio swaps it
    # into VTK's order when it writes VTK files.
    cells = [
        ("hexahedron", np.array(VOL_HEXES)),
        ("wedge", np.array([[w[0], w[2], w[1], w[3], w[5], w[4]] for w in VOL_WEDGES])),
        ("pyramid", np.array(VOL_PYRAMIDS)),
        ("triangle", np.array(VOL_TRIANGLES)),
    ]
    density = [np.array([1.0, 2.0]), np.array([3.0]), np.array([4.0]), np.array([9.0])]
    meshio.vtu.write(
        out("volcells.vtu"),
        meshio.Mesh(pts, cells, point_data={"height": height}, cell_data={"density": density}),
        binary=True,
    )
    meshio.vtk.write(
        out("volcells_51.vtk"),
        meshio.Mesh(pts, cells, point_data={"height": height}, cell_data={"density": density}),
        fmt_version="5.1",
        binary=False,
    )
    gmsh_cells = cells
    m = meshio.Mesh(pts, gmsh_cells, point_data={"height": height},
                    cell_data={"density": density})
    m.cell_data["gmsh:physical"] = [np.full(len(c.data), 1) for c in m.cells]
    m.cell_data["gmsh:geometrical"] = [np.full(len(c.data), 1) for c in m.cells]
    meshio.gmsh.write(out("volcells_22.msh"), m, fmt_version="2.2", binary=False)
    meshio.gmsh.write(out("volcells_22_binary.msh"), m, fmt_version="2.2", binary=True)

    # Cell data on the cube: density = tet index + 1, flow = (index, 2*index, 0).
    n = len(TETS)
    cube = cube_mesh()
    cube.cell_data = {
        "density": [np.arange(1.0, n + 1.0)],
        "flow": [np.array([[i, 2.0 * i, 0.0] for i in range(n)])],
    }
    meshio.vtu.write(out("cube_celldata.vtu"), cube, binary=True)
    meshio.vtk.write(out("cube_celldata_42.vtk"), cube, fmt_version="4.2", binary=True)
    cube.cell_data["gmsh:physical"] = [np.full(n, 1)]
    cube.cell_data["gmsh:geometrical"] = [np.full(n, 1)]
    meshio.gmsh.write(out("cube_celldata_41.msh"), cube, fmt_version="4.1", binary=False)

    # Quadratic tets: corners as in the cube, one node in the middle of each edge.
    quad_points = [tuple(p) for p in POINTS]
    mid = {}

    def midpoint(a, b):
        key = (min(a, b), max(a, b))
        if key not in mid:
            pa, pb = POINTS[a], POINTS[b]
            quad_points.append(tuple((pa[k] + pb[k]) / 2 for k in range(3)))
            mid[key] = len(quad_points) - 1
        return mid[key]

    tet10 = []
    for a, b, c, d in TETS:
        # VTK and gmsh order of the edges: 01 12 20 03 13 23 (gmsh: 01 12 20 03 23 13).
        tet10.append([a, b, c, d, midpoint(a, b), midpoint(b, c), midpoint(c, a),
                      midpoint(a, d), midpoint(b, d), midpoint(c, d)])
    qp = np.array(quad_points)
    temp = qp[:, 0] + 2.0 * qp[:, 1] + 3.0 * qp[:, 2]
    qm = meshio.Mesh(qp, [("tetra10", np.array(tet10))], point_data={"temperature": temp})
    meshio.vtu.write(out("quadratic.vtu"), qm, binary=False)
    meshio.gmsh.write(out("quadratic_22.msh"), qm, fmt_version="2.2", binary=False)

    # Medit (meshio's writer): the cube with element references 1..7.
    med = meshio.Mesh(
        np.array(POINTS), [("tetra", np.array(TETS)), ("triangle", np.array(TRIANGLES))],
        cell_data={"medit:ref": [np.arange(1, n + 1), np.array([20, 21])]},
    )
    meshio.medit.write(out("cube.mesh"), med)

    # gmsh 1.0, by hand: a $PhysicalNames-like unknown section, the cube and a triangle.
    s = "$NOD\n%d\n" % len(POINTS)
    s += "".join(f"{i + 1} {p[0]!r} {p[1]!r} {p[2]!r}\n" for i, p in enumerate(POINTS))
    s += "$ENDNOD\n$ELM\n%d\n" % (len(TETS) + 1)
    s += f"1 2 1 1 3 {TRIANGLES[0][0] + 1} {TRIANGLES[0][1] + 1} {TRIANGLES[0][2] + 1}\n"
    for e, t in enumerate(TETS):
        s += f"{e + 2} 4 1 1 4 " + " ".join(str(v + 1) for v in t) + "\n"
    s += "$ENDELM\n"
    out("cube_10.msh").write_text(s)
    # 1.0 with an element that announces 4 nodes and lists 3.
    out("bad_node_count_10.msh").write_text(s.replace("4 1 1 4 1 2 4 8", "4 1 1 4 1 2 4"))

    # Legacy ascii with CRLF line ends and blank lines between (and inside) sections.
    text = out("cube_42_ascii.vtk").read_text()
    text = text.replace("\nCELLS", "\n\n\nCELLS").replace("\nCELL_TYPES", "\n   \nCELL_TYPES")
    text = text.replace("\nPOINT_DATA", "\n\nPOINT_DATA")
    out("cube_42_blank_crlf.vtk").write_bytes(text.replace("\n", "\r\n").encode())

    # A bare mesh: no point or cell arrays.
    meshio.vtk.write(out("bare_42.vtk"),
                     meshio.Mesh(np.array(POINTS), [("tetra", np.array(TETS))]),
                     fmt_version="4.2", binary=False)

    # Surface only: the triangles of the cube's bottom.
    sm = meshio.Mesh(np.array(POINTS), [("triangle", np.array(TRIANGLES))],
                     point_data={"temperature": np.array(TEMPERATURE)})
    meshio.gmsh.write(out("surface_only.msh"), sm, fmt_version="2.2", binary=False)

    # Binary data that is not what the header declares.
    text = out("cube_binary.vtu").read_text()
    out("wrong_type.vtu").write_text(
        text.replace('type="Int64" Name="connectivity"', 'type="Int32" Name="connectivity"'))
    data = out("cube_42_binary.vtk").read_bytes()
    out("wrong_type.vtk").write_bytes(
        data.replace(f"POINTS {len(POINTS)} double".encode(),
                     f"POINTS {len(POINTS)} float".encode()))
    # A corrupted zlib block (bytes inside the compressed points changed).
    data = bytearray(out("cube_appended_raw_zlib.vtu").read_bytes())
    start = data.index(b"x\x9c", data.index(b"<AppendedData"))  # the first zlib stream
    for k in range(4, 10):
        data[start + k] ^= 0x5A
    out("corrupt_zlib.vtu").write_bytes(bytes(data))
    # A cell array whose header count disagrees with the cells.
    text = out("cube_celldata_42.vtk").read_bytes()
    out("bad_cell_data_count.vtk").write_bytes(
        text.replace(f"CELL_DATA {len(TETS)}".encode(), b"CELL_DATA 5"))


def main():
    if int(np.__version__.split(".")[0]) >= 2:
        raise SystemExit("gen-fixtures.py needs numpy < 2 (see the module docstring)")
    if OUT.exists():
        shutil.rmtree(OUT)
    OUT.mkdir(parents=True)
    write_meshio()
    write_vtu_appended()
    write_vtu_two_pieces()
    write_legacy_scalars()
    write_msh_tags()
    write_broken()
    write_import_fixtures()
    (OUT / "README.md").write_text(
        "Mesh-reader fixtures written by `scripts/gen-fixtures.py` (meshio "
        f"{meshio.__version__}); do not edit by hand, rerun the script.\n"
    )
    total = sum(p.stat().st_size for p in OUT.iterdir())
    print(f"wrote {len(list(OUT.iterdir()))} files, {total} bytes, to {OUT}")


if __name__ == "__main__":
    main()
