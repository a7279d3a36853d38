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


def dicom_volumes(out):
    """DICOM written by pydicom from anatomical.nii's voxels on CT_small.dcm's data set (new
    geometry, rescale 2·v − 1024): a series of extensionless slice files whose names and
    InstanceNumbers run in orders unrelated to their positions, the same with the rows running
    to the patient's right (ImageOrientationPatient [-1,0,0,0,1,0]), an RLE series, an enhanced
    CT (one file, per-frame positions in reverse order); pydicom's own CT series and RT dose;
    and what is refused. `add`'s expectation is what pydicom reads back."""
    import copy

    import pydicom
    from pydicom.data import get_testdata_file
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ExplicitVRLittleEndian, RLELossless, generate_uid

    arr, (sx, sy, sz) = anatomical()  # [x, y, z] i16
    zyx = np.ascontiguousarray(arr.transpose(2, 1, 0))
    nz, ny, nx = zyx.shape
    base = pydicom.dcmread(get_testdata_file("CT_small.dcm"))  # its preamble is a TIFF header
    slope, intercept = 2.0, -1024.0
    series_uid = None

    def image(ds):
        ds.SeriesInstanceUID = series_uid
        ds.SOPInstanceUID = generate_uid()
        ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        ds.Rows, ds.Columns = ny, nx
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1

    def read_series(d):
        """pydicom's reading: slices sorted along the normal, [x, y, z], rescaled."""
        dss = [pydicom.dcmread(os.path.join(d, f)) for f in os.listdir(d)]
        iop = np.array(dss[0].ImageOrientationPatient, float)
        n = np.cross(iop[:3], iop[3:])
        dss.sort(key=lambda ds: float(np.dot(np.array(ds.ImagePositionPatient, float), n)))
        vol = np.stack([ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
                        for ds in dss])
        return vol.transpose(2, 1, 0), np.array(dss[0].ImagePositionPatient, float)

    origin = np.array([-10.0, 20.0, 30.0])
    for name, iop, axes, rle in [
        ("dicom_series", (1, 0, 0, 0, 1, 0), [(0, False), (1, False), (2, False)], False),
        ("dicom_flipped", (-1, 0, 0, 0, 1, 0), [(0, True), (1, False), (2, True)], False),
        ("dicom_rle", (1, 0, 0, 0, 1, 0), [(0, False), (1, False), (2, False)], True),
    ]:
        d = os.path.join(out, name)
        os.makedirs(d, exist_ok=True)
        series_uid = generate_uid()
        n = np.cross(iop[:3], iop[3:])
        order = np.random.default_rng(0).permutation(nz)
        for k in range(nz):
            ds = copy.deepcopy(base)
            image(ds)
            ds.PixelSpacing = [sy, sx]  # between rows (y), between columns (x)
            ds.ImageOrientationPatient = list(iop)
            ds.ImagePositionPatient = [float(v) for v in origin + k * sz * n]
            ds.InstanceNumber = int(order[k]) + 1
            ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
            ds.PixelData = zyx[k].astype("<i2").tobytes()
            if rle:
                ds.compress(RLELossless)
            else:
                ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
            ds.save_as(os.path.join(d, f"IM{int(order[k]) * 7 % 1000:04d}"),
                       enforce_file_format=True)
        file_xyz, first = read_series(d)
        world = world_array(file_xyz, axes)
        # the world box's low corner: the first slice's position, less the flipped axes' extent
        low = first.copy()
        for a, (w, flip) in enumerate(axes):
            if flip:
                low[w] -= (world.shape[w] - 1) * (sx, sy, sz)[a]
        add(out, name, d, world, (sx, sy, sz), origin=low, note="pydicom")

    # enhanced CT: one file, frames in reverse z order, per-frame positions
    series_uid = generate_uid()
    ds = copy.deepcopy(base)
    for kw in ["ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing",
               "RescaleSlope", "RescaleIntercept", "SliceLocation"]:
        if kw in ds:
            delattr(ds, kw)
    image(ds)
    ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.2.1"  # Enhanced CT Image Storage
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID
    ds.NumberOfFrames = nz
    po, pm, pv = Dataset(), Dataset(), Dataset()
    po.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
    pm.PixelSpacing, pm.SliceThickness = [sy, sx], sz
    pv.RescaleSlope, pv.RescaleIntercept, pv.RescaleType = slope, intercept, "HU"
    shared = Dataset()
    shared.PlaneOrientationSequence = Sequence([po])
    shared.PixelMeasuresSequence = Sequence([pm])
    shared.PixelValueTransformationSequence = Sequence([pv])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for f in range(nz):
        pp = Dataset()
        pp.ImagePositionPatient = [1.0, 2.0, 3.0 + (nz - 1 - f) * sz]
        fg = Dataset()
        fg.PlanePositionSequence = Sequence([pp])
        frames.append(fg)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelData = np.ascontiguousarray(zyx[::-1]).astype("<i2").tobytes()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    p = os.path.join(out, "dicom_enhanced.dcm")
    ds.save_as(p, enforce_file_format=True)
    back = pydicom.dcmread(p).pixel_array[::-1] * slope + intercept  # frames sorted by z
    add(out, "dicom_enhanced", p, back.transpose(2, 1, 0), (sx, sy, sz), origin=(1, 2, 3),
        note="pydicom enhanced CT")

    # pydicom's own files
    tests = os.path.dirname(get_testdata_file("CT_small.dcm"))
    d = os.path.join(out, "dicom_ct5n")
    shutil.copytree(os.path.join(tests, "dicomdirtests", "98892001", "CT5N"), d,
                    dirs_exist_ok=True)
    world, first = read_series(d)
    ps = pydicom.dcmread(os.path.join(d, os.listdir(d)[0])).PixelSpacing
    add(out, "dicom_ct5n", d, world, (float(ps[1]), float(ps[0]), 2.5), origin=first,
        note="pydicom dicomdirtests CT5N")
    p = os.path.join(out, "rtdose.dcm")
    shutil.copyfile(os.path.join(tests, "rtdose.dcm"), p)
    ds = pydicom.dcmread(p)
    dose = ds.pixel_array * float(ds.DoseGridScaling)  # [frame, y, x]
    add(out, "rtdose", p, dose.transpose(2, 1, 0), (10, 10, 5),
        origin=[float(v) for v in ds.ImagePositionPatient], note="pydicom RT dose")
    for name, src, error in [
        ("dicom_gap", ("dicomdirtests", "77654033", "CT2"), "gaps"),
        ("dicom_three_series", ("dicomdirtests", "98892003", "MR2"), "3 series"),
        ("dicom_oblique", ("dicomdirtests", "98892003", "MR700"), "ImageOrientationPatient"),
    ]:
        d = os.path.join(out, name)
        shutil.copytree(os.path.join(tests, *src), d, dirs_exist_ok=True)
        refuse(out, name, d, error, note="pydicom dicomdirtests")
    for f, error in [("CT_small.dcm", "one 2D slice"), ("JPEG2000.dcm", "JPEG 2000")]:
        p = os.path.join(out, f)
        shutil.copyfile(os.path.join(tests, f), p)
        refuse(out, f.split(".")[0], p, error, note="pydicom")


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    nifti(out)
    zarr_volumes(out)
    nrrd_volumes(out)
    vtk_volumes(out)
    tiff_volumes(out)
    dicom_volumes(out)
    with open(os.path.join(out, "cases.json"), "w") as f:
        json.dump(CASES, f, indent=1)
    print(f"{len(CASES)} volume files in {out}")


if __name__ == "__main__":
    main()
