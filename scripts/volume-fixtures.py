#!/usr/bin/env python3
"""Volume files nobody here wrote, and what their own libraries read of them.

Writes into OUT (argument 1) the volume files of tests/volumes (server/tests/volumes.rs reads
them) and `cases.json`: for each file the prepare arguments it needs beyond the file (`--frame`,
`--scalar`), and what the Python library that reads the format reads of it: world dims,
spacing, value range, and every voxel, in the world frame tetwave uses (axes ascending, x
fastest) as little-endian f64 (`<name>.f64`), so that `verify --input <name>.f64 --dims ...
--dtype f64` checks the store voxel by voxel against the library's reading and not only against
tetwave's own reader.

The files: test data shipped in PyPI wheels (nibabel's NIfTI files, pydicom's DICOM files), and
volumes written by tifffile, pynrrd, zarr-python and VTK's own writers from those files' voxels.
"""

import json
import os
import shutil
import sys

import numpy as np

CASES = []


def world_array(arr, axes):
    """arr indexed [i, j, k] along the file's axes (i fastest in the file); axes[a] = (world
    axis, flip) of file axis a. Returns the array indexed [x, y, z] along the world axes,
    ascending."""
    for a, (_, flip) in enumerate(axes):
        if flip:
            arr = np.flip(arr, axis=a)
    order = [0, 0, 0]
    for a, (w, _) in enumerate(axes):
        order[w] = a
    return np.transpose(arr, order)


def add(out, name, path, world, spacing, args=(), origin=None, note=""):
    """One case: `world` indexed [x, y, z] (float64 values as the library reads them)."""
    world = np.asarray(world, dtype=np.float64)
    assert world.ndim == 3, (name, world.shape)
    if np.isnan(world).any():
        # prepare refuses NaN samples unless told what to put there
        world = np.where(np.isnan(world), 0.0, world)
        args = list(args) + ["--nan-as", "0"]
    raw = f"{name}.f64"
    world.ravel(order="F").astype("<f8").tofile(os.path.join(out, raw))
    CASES.append(
        {
            "name": name,
            "path": os.path.relpath(path, out),
            "args": list(args),
            "dims": list(world.shape),
            "spacing": [float(s) for s in spacing],
            "origin": None if origin is None else [float(o) for o in origin],
            "range": [float(world.min()), float(world.max())],
            "expect": raw,
            "note": note,
        }
    )


def nifti(out):
    import nibabel as nib

    data = os.path.join(os.path.dirname(nib.__file__), "tests", "data")
    for f in [
        "anatomical.nii",  # big-endian i16, LAS
        "standard.nii.gz",  # u8, sform only, gzip
        "reoriented_anat_moved.nii",  # big-endian f32, RAS
        "resampled_anat_moved.nii",  # big-endian f32, LAS
    ]:
        dst = os.path.join(out, f)
        shutil.copyfile(os.path.join(data, f), dst)
        img = nib.as_closest_canonical(nib.load(dst))
        name = f.split(".")[0]
        add(out, name, dst, img.get_fdata(dtype=np.float64), img.header.get_zooms()[:3],
            origin=img.affine[:3, 3], note="nibabel")
    # oblique: refused
    for f in ["example4d.nii.gz", "example_nifti2.nii.gz"]:
        dst = os.path.join(out, f)
        shutil.copyfile(os.path.join(data, f), dst)
        refuse(out, f.split(".")[0], dst, "oblique", ["--frame", "0"], "nibabel")
    # 4D, NIfTI-2, gzip, scaled: anatomical's voxels as two frames, written by nibabel
    src = nib.load(os.path.join(data, "anatomical.nii"))
    a = np.asarray(src.dataobj).astype(np.int16)
    four = np.stack([a, a // 2], axis=-1)
    img = nib.Nifti2Image(four, src.affine)
    img.header.set_slope_inter(0.5, -3.0)
    dst = os.path.join(out, "anatomical4d.nii.gz")
    nib.save(img, dst)
    img = nib.as_closest_canonical(nib.load(dst))
    add(out, "anatomical4d", dst, img.get_fdata(dtype=np.float64)[..., 1],
        img.header.get_zooms()[:3], ["--frame", "1"], img.affine[:3, 3], "nibabel NIfTI-2")


def refuse(out, name, path, error, args=(), note=""):
    """A file tetwave refuses, with a message holding `error`."""
    CASES.append({"name": name, "path": os.path.relpath(path, out), "args": list(args),
                  "error": error, "note": note})


def zarr_volumes(out):
    """Zarr arrays and OME-Zarr images written by zarr-python 3 from anatomical.nii's voxels
    (nibabel's canonical RAS array, int16, [x, y, z]); `add`'s expectation is what zarr-python
    reads back."""
    import nibabel as nib
    import numcodecs
    import zarr
    from zarr.codecs import BloscCodec, GzipCodec, ZstdCodec

    data = os.path.join(os.path.dirname(nib.__file__), "tests", "data")
    img = nib.as_closest_canonical(nib.load(os.path.join(data, "anatomical.nii")))
    world = np.asarray(img.dataobj).astype(np.int16)  # [x, y, z]
    zyx = np.ascontiguousarray(world.transpose(2, 1, 0))  # C order: x fastest
    ch = tuple(max(2, n // 3) for n in zyx.shape)

    def fresh(name):
        p = os.path.join(out, name)
        shutil.rmtree(p, ignore_errors=True)
        return p

    # plain arrays: spacing 1, dims z, y, x
    for name, kw in [
        ("zarr2_blosc", dict(zarr_format=2, compressors=numcodecs.Blosc("lz4", 5, 1))),
        ("zarr2_f_zlib", dict(zarr_format=2, order="F", compressors=numcodecs.Zlib(5))),
        ("zarr2_be_gzip", dict(zarr_format=2, dtype=">i2", compressors=numcodecs.GZip(5))),
        ("zarr3_zstd", dict(zarr_format=3)),
        ("zarr3_blosc", dict(zarr_format=3, compressors=BloscCodec(cname="zstd", clevel=3,
                                                                    shuffle="bitshuffle"))),
        ("zarr3_sharded", dict(zarr_format=3, shards=tuple(2 * c for c in ch),
                               compressors=GzipCodec(level=5))),
    ]:
        p = fresh(name + ".zarr")
        kw.setdefault("dtype", zyx.dtype)
        a = zarr.create_array(p, shape=zyx.shape, chunks=ch, **kw)
        a[:] = zyx
        back = zarr.open_array(p, mode="r")[:]
        add(out, name, p, back.transpose(2, 1, 0), (1, 1, 1), origin=(0, 0, 0),
            note="zarr-python")

    # OME-Zarr 0.4 (v2 group) and 0.5 (v3 group): two levels of (c, z, y, x) with two
    # channels (the voxels, and half of them); the dataset's scale and translation, then the
    # multiscale's scale of 2
    dx, dy, dz = (float(s) for s in img.header.get_zooms()[:3])
    two = np.stack([zyx, zyx // 2])
    axes = [{"name": "c", "type": "channel"}] + [
        {"name": n, "type": "space", "unit": "millimeter"} for n in "zyx"]
    datasets = [{"path": str(k), "coordinateTransformations": [
        {"type": "scale", "scale": [1.0, dz * 2**k, dy * 2**k, dx * 2**k]},
        {"type": "translation", "translation": [0.0, -5.0, 7.0, 3.0]}]} for k in range(2)]
    ms = {"name": "anatomical", "axes": axes, "datasets": datasets,
          "coordinateTransformations": [{"type": "scale", "scale": [1.0, 2.0, 2.0, 2.0]}]}
    omero = {"channels": [{"label": "T1", "color": "FFFFFF"}, {"label": "half", "color": "FF0000"}]}
    for fmt, version, choice in ((2, "0.4", "half"), (3, "0.5", "1")):
        p = fresh(f"ome{version.replace('.', '')}.zarr")
        g = zarr.open_group(p, mode="w", zarr_format=fmt)
        if fmt == 2:
            g.attrs.update({"multiscales": [dict(ms, version="0.4")], "omero": omero})
        else:
            g.attrs.update({"ome": {"version": "0.5", "multiscales": [ms], "omero": omero}})
        for k in range(2):
            level = two[:, :: 2**k, :: 2**k, :: 2**k]
            a = g.create_array(str(k), shape=level.shape, chunks=(1,) + ch, dtype=level.dtype,
                               **({"dimension_names": ["c", "z", "y", "x"]} if fmt == 3 else {}))
            a[:] = level
        back = zarr.open_group(p, mode="r")["0"][1]
        add(out, f"ome{version.replace('.', '')}", p, back.transpose(2, 1, 0),
            (2 * dx, 2 * dy, 2 * dz), ["--scalar", choice], origin=(6.0, 14.0, -10.0),
            note=f"zarr-python, OME-Zarr {version}")
    # refused: 64-bit integers; a 4D array without axes (which dim is time, which channels?)
    p = fresh("zarr3_int64.zarr")
    zarr.create_array(p, shape=zyx.shape, chunks=ch, dtype="int64")[:] = zyx
    refuse(out, "zarr3_int64", p, "int64", note="zarr-python")
    p = fresh("zarr3_4d.zarr")
    zarr.create_array(p, shape=two.shape, chunks=(1,) + ch, dtype=two.dtype)[:] = two
    refuse(out, "zarr3_4d", p, "OME-Zarr", note="zarr-python")


def anatomical():
    """nibabel's anatomical.nii (33×41×25 i16) as [x, y, z], canonical RAS, and its spacing."""
    import nibabel as nib

    data = os.path.join(os.path.dirname(nib.__file__), "tests", "data")
    img = nib.as_closest_canonical(nib.load(os.path.join(data, "anatomical.nii")))
    return np.asarray(img.dataobj).astype(np.int16), tuple(float(z) for z in img.header.get_zooms()[:3])


def nrrd_volumes(out):
    """NRRD files written by pynrrd from anatomical.nii's voxels: raw, gzip, ascii, detached
    headers, big-endian, a vector axis (--scalar) and a time axis (--frame); LPS, axis-aligned."""
    import nrrd

    arr, spacing = anatomical()
    origin = [10.0, -5.0, 2.5]
    hdr = {"space": "left-posterior-superior", "space directions": np.diag(spacing).astype(float),
           "space origin": np.array(origin), "kinds": ["domain"] * 3, "endian": "little"}
    cases = []
    for enc in ["raw", "gzip", "ascii"]:
        p = f"{out}/vol_{enc}.nrrd"
        nrrd.write(p, arr, dict(hdr, encoding=enc))
        cases.append((f"nrrd_{enc}", p, []))
    for enc in ["raw", "gzip"]:
        p = f"{out}/vol_detached_{enc}.nhdr"
        nrrd.write(p, arr, dict(hdr, encoding=enc), detached_header=True)
        cases.append((f"nrrd_detached_{enc}", p, []))
    p = f"{out}/vol_big.nrrd"
    nrrd.write(p, arr, dict(hdr, encoding="raw", endian="big"))
    cases.append(("nrrd_big", p, []))
    for name, p, args in cases:
        back, _ = nrrd.read(p)
        add(out, name, p, back, spacing, args, origin, "pynrrd")
    p = f"{out}/vec.nrrd"
    nrrd.write(p, np.stack([arr, -arr, 2 * arr], 0),
               {"kinds": ["vector", "domain", "domain", "domain"], "encoding": "raw", "space": "RAS",
                "space directions": np.vstack([np.full(3, np.nan), np.diag(spacing)]),
                "space origin": [0.0, 0.0, 0.0]})
    back, _ = nrrd.read(p)
    add(out, "nrrd_vector", p, back[1], spacing, ["--scalar", "1"], [0, 0, 0], "pynrrd")
    p = f"{out}/time.nrrd"
    nrrd.write(p, np.stack([arr, arr + 100], 3),
               {"kinds": ["domain", "domain", "domain", "time"], "encoding": "gzip",
                "spacings": [*spacing, np.nan]})
    back, _ = nrrd.read(p)
    add(out, "nrrd_time", p, back[..., 1], spacing, ["--frame", "1"], [0, 0, 0], "pynrrd")


def vtk_volumes(out):
    """VTK image data written by VTK's own writers from anatomical.nii's voxels: .vti in every
    data mode (ascii, binary, appended raw and base64), uncompressed and zlib, and legacy
    STRUCTURED_POINTS ascii and binary; a scalar array and a 3-component one (--scalar)."""
    import vtk
    from vtk.util import numpy_support as ns

    arr, spacing = anatomical()
    img = vtk.vtkImageData()
    img.SetDimensions(*arr.shape)
    img.SetSpacing(*spacing)
    img.SetOrigin(1, 2, 3)
    f = arr.ravel(order="F")
    a = ns.numpy_to_vtk(f, deep=True)
    a.SetName("density")
    img.GetPointData().SetScalars(a)
    v = ns.numpy_to_vtk(np.stack([f, -f, 2 * f], 1).astype(np.float32), deep=True)
    v.SetName("vel")
    img.GetPointData().AddArray(v)
    files = []
    for mode in ["Ascii", "Binary", "Appended"]:
        for comp in ["None", "ZLib"]:
            for enc in ([0, 1] if mode == "Appended" else [1]):
                w = vtk.vtkXMLImageDataWriter()
                w.SetInputData(img)
                getattr(w, "SetDataModeTo" + mode)()
                getattr(w, "SetCompressorTypeTo" + comp)()
                w.SetEncodeAppendedData(enc)
                w.SetBlockSize(1000)
                p = f"{out}/img_{mode}_{comp}_{'b64' if enc else 'raw'}.vti"
                w.SetFileName(p)
                w.Write()
                files.append(p)
    for ft, name in [(1, "ascii"), (2, "binary")]:
        w = vtk.vtkStructuredPointsWriter()
        w.SetInputData(img)
        w.SetFileType(ft)
        p = f"{out}/img_{name}.vtk"
        w.SetFileName(p)
        w.Write()
        files.append(p)
    for p in files:
        r = vtk.vtkXMLImageDataReader() if p.endswith(".vti") else vtk.vtkStructuredPointsReader()
        r.SetFileName(p)
        r.Update()
        o = r.GetOutput()
        dims = o.GetDimensions()
        d = ns.vtk_to_numpy(o.GetPointData().GetArray("density")).reshape(dims, order="F")
        vel = ns.vtk_to_numpy(o.GetPointData().GetArray("vel"))[:, 2].reshape(dims, order="F")
        name = "vtk_" + os.path.basename(p).replace(".", "_")
        add(out, name, p, d, o.GetSpacing(), ["--scalar", "density"], o.GetOrigin(), "vtk")
        if p.endswith("Appended_ZLib_raw.vti") or p.endswith("binary.vtk"):
            add(out, name + "_vel2", p, vel, o.GetSpacing(), ["--scalar", "vel:2"], o.GetOrigin(), "vtk")


def tiff_volumes(out):
    """TIFF stacks written by tifffile from anatomical.nii's voxels: ImageJ with spacing and unit,
    plain, zlib, LZW, PackBits, zstd, predictor, tiled, BigTIFF, big-endian, and a folder of
    slices (with a README among them)."""
    import tifffile

    arr, (sx, sy, sz) = anatomical()
    zyx = np.ascontiguousarray(arr.transpose(2, 1, 0))
    plain = dict(photometric="minisblack")
    files = {
        "imagej": dict(imagej=True, resolution=(1 / sx, 1 / sy),
                       metadata={"spacing": sz, "unit": "um", "axes": "ZYX"}),
        "plain": plain,
        "zlib": dict(plain, compression="zlib"),
        "lzw": dict(plain, compression="lzw"),
        "packbits": dict(plain, compression="packbits"),
        "zstd": dict(plain, compression="zstd"),
        "predictor": dict(plain, compression="zlib", predictor=True),
        "tiled": dict(plain, tile=(16, 16), compression="zlib"),
        "bigtiff": dict(plain, bigtiff=True),
        "bigendian": dict(plain, byteorder=">", rowsperstrip=3),
    }
    for name, kw in files.items():
        p = os.path.join(out, f"tiff_{name}.tif")
        tifffile.imwrite(p, zyx, **kw)
        back = tifffile.imread(p)
        spacing = (sx, sy, sz) if name == "imagej" else (1, 1, 1)
        add(out, f"tiff_{name}", p, back.transpose(2, 1, 0), spacing, origin=(0, 0, 0),
            note="tifffile")
    d = os.path.join(out, "tiff_slices")
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "README.txt"), "w") as f:
        f.write("slices of anatomical.nii\n")
    for k in range(zyx.shape[0]):
        tifffile.imwrite(os.path.join(d, f"slice_{k}.tif"), zyx[k], **plain)
    back = np.stack([tifffile.imread(os.path.join(d, f"slice_{k}.tif"))
                     for k in range(zyx.shape[0])])
    add(out, "tiff_slices", d, back.transpose(2, 1, 0), (1, 1, 1), origin=(0, 0, 0),
        note="tifffile")


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    nifti(out)
    zarr_volumes(out)
    nrrd_volumes(out)
    vtk_volumes(out)
    tiff_volumes(out)
    with open(os.path.join(out, "cases.json"), "w") as f:
        json.dump(CASES, f, indent=1)
    print(f"{len(CASES)} volume files in {out}")


if __name__ == "__main__":
    main()
