"""Elevation inputs read by windows, never whole (except ``.npz``, whose members zip stores).

Every source exposes ``rows``, ``cols``, ``dtype``, ``nodata``, ``crs`` (WKT or None),
``transform`` (GDAL 6-tuple ``(x0, dx, 0, y0, 0, -dy)`` or None), ``name``, and
``read(r0, r1, c0, c1) -> float32 (r1-r0, c1-c0)`` with nodata samples as NaN. Integer inputs
are converted to float32 (exact for 16-bit and for 32-bit values below 2^24).

Formats: GeoTIFF / Cloud-Optimized GeoTIFF and any other raster GDAL reads (rasterio, windowed:
``.vrt``, ``.img``, ``.asc``, ``.bil``, NetCDF, a zipped SRTM tile), ``.npy`` (row reads),
SRTM ``.hgt`` (big-endian int16, 1201² or 3601², georeferenced from the file name),
``.npz`` (a named array), raw binary (explicit shape and dtype), and the synthetic generator.

Georeference of inputs that carry none (``.npy``, ``.npz``, raw, plain TIFF): a sidecar
``FILE.json`` beside the input (``{"spacing": [dx, dy], "crs": "EPSG:..." | null}``, written by
``massview generate terrain --format npy``), or ``spacing``/``crs`` given to :func:`open_source`
(``prepare terrain --spacing DX[,DY] --crs CRS``), which win over the sidecar. Spacing is in
the CRS's units (metres without a CRS). Without either, 1 m is assumed (and ``prepare`` warns).
"""

from __future__ import annotations

import math
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...core.errors import IngestError

__all__ = ["RasterSource", "open_source", "ArraySource", "crs_name", "sidecar_path", "write_sidecar", "parse_spacing",
           "OrthoPlacement", "place_ortho"]


class RasterSource:
    rows: int
    cols: int
    dtype: np.dtype
    nodata: float | None = None
    crs: str | None = None
    transform: tuple[float, ...] | None = None
    name: str = ""
    stamp: list | None = None  # a file input's [size, mtime_ns] (open_source): a resumed prepare checks it
    anchored: bool = True  # the transform places the raster (False: only a spacing was given, origin 0, 0)
    bands: int = 1  # bands in the file (the elevation is band 1)

    def _raw(self, r0, r1, c0, c1) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        try:
            a = np.asarray(self._raw(r0, r1, c0, c1))
        except (OSError, ValueError) as e:
            raise IngestError(f"{self.name}: could not read rows {r0}:{r1}, cols {c0}:{c1} ({e}); the file may be truncated or corrupt") from None
        out = a.astype(np.float32)
        if self.nodata is not None and not (isinstance(self.nodata, float) and math.isnan(self.nodata)):
            out[a == self.nodata] = np.nan
        out[~np.isfinite(out)] = np.nan
        return out

    def read_rgb(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """(h, w, 3) uint8 colour of a window (orthophotos)."""
        raise IngestError(f"{self.name}: not an RGB image; give a GeoTIFF with at least 3 bands as --color")

    def spacing(self) -> tuple[float, float]:
        """Sample spacing (dx, dy) in metres: from the transform, converting degrees at the
        centre latitude for geographic CRSs; (1, 1) without a transform."""
        if not self.transform:
            return 1.0, 1.0
        dx, dy = abs(self.transform[1]), abs(self.transform[5])
        if self.crs and _is_geographic(self.crs):
            lat = self.transform[3] + self.transform[5] * self.rows / 2
            m = 111_320.0
            return dx * m * max(math.cos(math.radians(lat)), 1e-6), dy * m
        f = self.linear_unit()[1]
        return dx * f, dy * f

    def linear_unit(self) -> tuple[str, float]:
        """(name, metres per unit) of a projected CRS's axes (``("metre", 1.0)`` without a CRS,
        or when it cannot be read): the spacing is converted by it, so 100 ft pixels are 30.48 m."""
        if not self.crs or _is_geographic(self.crs):
            return "metre", 1.0
        try:
            from rasterio.crs import CRS

            name, f = CRS.from_user_input(self.crs).linear_units_factor
            return str(name), float(f)
        except Exception:  # noqa: BLE001 - an unparsable or unit-less CRS: metres, as before
            return "metre", 1.0


def crs_name(wkt: str) -> str:
    """A short name (e.g. ``EPSG:32632``) for a WKT CRS, or its first characters."""
    try:
        from rasterio.crs import CRS

        return CRS.from_wkt(wkt).to_string() or wkt[:60]
    except Exception:  # noqa: BLE001
        return wkt[:60]


def _is_geographic(crs: str) -> bool:
    try:
        from rasterio.crs import CRS

        return bool(CRS.from_user_input(crs).is_geographic)
    except Exception:  # noqa: BLE001 - an unparsable CRS is treated as projected
        return crs.upper().startswith("GEOGCS")


class ArraySource(RasterSource):
    """Any 2-D array-like (numpy array, memmap, zarr array)."""

    def __init__(self, arr, name: str, nodata=None, crs=None, transform=None):
        if getattr(arr, "ndim", 0) != 2:
            raise IngestError(f"{name}: expected a 2-D elevation array, got shape {getattr(arr, 'shape', '?')}; give a single band")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise IngestError(f"{name}: dtype {arr.dtype} is not numeric")
        self.arr, self.name = arr, name
        self.rows, self.cols = (int(v) for v in arr.shape)
        self.dtype = np.dtype(arr.dtype)
        self.nodata, self.crs, self.transform = nodata, crs, transform

    def _raw(self, r0, r1, c0, c1):
        return self.arr[r0:r1, c0:c1]


class BinaryFileSource(RasterSource):
    """A C-ordered 2-D array at a byte offset of a file (``.npy`` body, raw binary), read by
    plain file reads of whole rows — unlike a memory map, pages read once do not stay in the
    process's resident memory."""

    def __init__(self, path: Path, shape: tuple[int, int], dtype, offset: int, name: str):
        self.path, self.offset, self.name = path, int(offset), name
        self.rows, self.cols = (int(v) for v in shape)
        self.dtype = np.dtype(dtype)

    def _raw(self, r0, r1, c0, c1):
        row = self.cols * self.dtype.itemsize
        with open(self.path, "rb") as f:  # one open per window: nothing held between reads
            f.seek(self.offset + r0 * row)
            buf = f.read((r1 - r0) * row)
        if len(buf) != (r1 - r0) * row:
            raise OSError(f"file ends early: wanted {(r1 - r0) * row} bytes at row {r0}")
        return np.frombuffer(buf, self.dtype).reshape(r1 - r0, self.cols)[:, c0:c1]

    def read_float32_into(self, r0: int, out: np.ndarray) -> bool:
        """Rows ``r0 .. r0 + len(out)`` (all columns) straight into ``out`` ((n, cols) float32,
        C-contiguous) with one ``readinto``, when the file holds native float32 and no nodata
        value is set: what :meth:`read` returns then, without its copies. False (``out``
        untouched) when it does not apply; the caller then uses :meth:`read`."""
        if self.dtype != np.dtype(np.float32) or self.nodata is not None or not out.flags.c_contiguous \
                or out.dtype != np.float32 or out.shape[1:] != (self.cols,):
            return False
        with open(self.path, "rb", buffering=0) as f:
            f.seek(self.offset + r0 * self.cols * 4)
            got = f.readinto(memoryview(out.reshape(-1)).cast("B"))
        if got != out.nbytes:
            raise IngestError(f"{self.name}: could not read rows {r0}:{r0 + out.shape[0]} (the file ends early); "
                              "the file may be truncated or corrupt")
        return True


def _npy_source(p: Path) -> RasterSource:
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(f)
            offset = f.tell()
    except ValueError as e:
        raise IngestError(f"{p}: not a readable .npy file ({e})") from None
    if len(shape) != 2:
        raise IngestError(f"{p}: expected a 2-D elevation array, got shape {shape}; give a single band")
    if fortran:
        return ArraySource(np.load(p, mmap_mode="r"), p.name)
    if not (np.issubdtype(dtype, np.floating) or np.issubdtype(dtype, np.integer)):
        raise IngestError(f"{p}: dtype {dtype} is not numeric")
    return BinaryFileSource(p, shape, dtype, offset, p.name)


class GeoTiffSource(RasterSource):
    def __init__(self, path: Path, band: int = 1):
        import warnings

        import rasterio

        try:
            with warnings.catch_warnings():  # a plain (non-georeferenced) TIFF is fine: transform None
                warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
                self.ds = rasterio.open(path)
        except rasterio.errors.RasterioIOError as e:
            raise IngestError(f"{path}: cannot open as a raster ({e})") from None
        if band > self.ds.count:
            raise IngestError(f"{path}: has {self.ds.count} band(s), band {band} requested")
        self.band, self.name, self.bands = band, path.name, self.ds.count
        self.rows, self.cols = self.ds.height, self.ds.width
        self.dtype = np.dtype(self.ds.dtypes[band - 1])
        self.nodata = self.ds.nodatavals[band - 1]
        self.crs = self.ds.crs.to_wkt() if self.ds.crs else None
        t = self.ds.transform
        self.transform = None if t.is_identity else (t.c, t.a, t.b, t.f, t.d, t.e)
        self.flipped = False  # rows stored south to north (a positive pixel height): read bottom-up
        if self.transform is not None:
            if t.b != 0 or t.d != 0:
                raise IngestError(f"{path}: its georeference is rotated or sheared (transform {t.a:g}, {t.b:g}, {t.d:g}, {t.e:g}); "
                                  "warp it to a north-up grid first, e.g. `gdalwarp -t_srs <its CRS> IN OUT.tif`")
            if t.a < 0:
                raise IngestError(f"{path}: its columns run west (pixel width {t.a:g}); warp it to a north-up grid first (gdalwarp)")
            if t.e > 0:  # south-up: row 0 is the southern edge; massview's row 0 is the northern one
                self.flipped = True
                self.transform = (t.c, t.a, 0.0, t.f + t.e * self.rows, 0.0, -t.e)
        scale, offset = float(self.ds.scales[band - 1] or 1.0), float(self.ds.offsets[band - 1] or 0.0)
        self.scale_offset = None if (scale, offset) == (1.0, 0.0) else (scale, offset)

    def _raw(self, r0, r1, c0, c1):
        from rasterio.windows import Window

        if self.flipped:
            a = self.ds.read(self.band, window=Window(c0, self.rows - r1, c1 - c0, r1 - r0))
            return a[::-1]
        return self.ds.read(self.band, window=Window(c0, r0, c1 - c0, r1 - r0))

    def read(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """As :meth:`RasterSource.read`, with the band's scale and offset tags applied (height =
        value · scale + offset, after the nodata value is masked on the stored values)."""
        out = super().read(r0, r1, c0, c1)
        if self.scale_offset is not None:
            scale, offset = self.scale_offset
            out *= np.float32(scale)
            out += np.float32(offset)
        return out

    def read_rgb(self, r0, r1, c0, c1):
        from rasterio.windows import Window

        if self.ds.count < 3:
            return super().read_rgb(r0, r1, c0, c1)
        a = self.ds.read([1, 2, 3], window=Window(c0, r0, c1 - c0, r1 - r0))
        if a.dtype != np.uint8:  # scale other types to 0..255
            lo, hi = float(a.min()), float(a.max())
            a = ((a - lo) * (255.0 / max(hi - lo, 1e-9))).astype(np.uint8)
        return np.moveaxis(a, 0, -1)


class HgtSource(ArraySource):
    """SRTM ``.hgt``: square big-endian int16, nodata -32768; SW corner from the file name."""

    def __init__(self, path: Path):
        size = path.stat().st_size
        side = int(round(math.sqrt(size / 2)))
        if side * side * 2 != size or side not in (1201, 3601):
            raise IngestError(f"{path}: {size} bytes is not an SRTM tile (1201² or 3601² int16 samples)")
        arr = np.memmap(path, dtype=">i2", mode="r", shape=(side, side))
        crs, transform = None, None
        mt = re.match(r"([NS])(\d{2})([EW])(\d{3})", path.name.upper())
        if mt:
            lat = int(mt.group(2)) * (1 if mt.group(1) == "N" else -1)
            lon = int(mt.group(4)) * (1 if mt.group(3) == "E" else -1)
            d = 1.0 / (side - 1)
            crs = 'GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AXIS["Latitude",NORTH],AXIS["Longitude",EAST],AUTHORITY["EPSG","4326"]]'
            transform = (lon - d / 2, d, 0.0, lat + 1 + d / 2, 0.0, -d)
        super().__init__(arr, path.name, nodata=-32768, crs=crs, transform=transform)


def sidecar_path(path) -> Path:
    """The georeference sidecar of an input file: ``FILE.json`` beside ``FILE``."""
    p = Path(path)
    return p.with_name(p.name + ".json")


def write_sidecar(path, spacing: tuple[float, float], crs: str | None = None) -> Path:
    """Record the sample spacing (and CRS) of an input without a georeference of its own."""
    import json

    side = sidecar_path(path)
    side.write_text(json.dumps({"spacing": [float(spacing[0]), float(spacing[1])], "crs": crs}) + "\n")
    return side


def parse_spacing(spec, what: str = "--spacing") -> tuple[float, float]:
    """``DX`` or ``DX,DY`` (or a number, or a 2-sequence) -> (dx, dy), both finite and positive."""
    try:
        vals = [float(v) for v in (spec.split(",") if isinstance(spec, str) else [spec] if isinstance(spec, (int, float)) else spec)]
    except (TypeError, ValueError):
        raise IngestError(f"{what} {spec!r}: expected DX or DX,DY (sample spacing, e.g. 30 or 30,30)") from None
    if len(vals) == 1:
        vals *= 2
    if len(vals) != 2 or not all(math.isfinite(v) and v > 0 for v in vals):
        raise IngestError(f"{what} {spec!r}: expected one or two positive numbers, DX or DX,DY")
    return vals[0], vals[1]


def _crs_wkt(crs: str, what: str) -> str:
    try:
        from rasterio.crs import CRS

        return CRS.from_user_input(crs).to_wkt()
    except Exception as e:  # noqa: BLE001 - rasterio raises CRSError and others
        raise IngestError(f"{what} {crs!r}: not a CRS rasterio understands ({e}); give e.g. EPSG:32632 or a WKT string") from None


def _georeference(src: RasterSource, p: Path, spacing, crs) -> None:
    """Apply the sidecar, then explicit spacing/CRS, to a source (see the module docstring)."""
    side = sidecar_path(p)
    if src.transform is None and spacing is None and side.exists():
        import json

        try:
            meta = json.loads(side.read_text())
            spacing, crs = meta["spacing"], crs or meta.get("crs")
        except (ValueError, KeyError, TypeError) as e:
            raise IngestError(f"{side}: not a georeference sidecar ({e}); expected {{\"spacing\": [dx, dy], \"crs\": ...}}") from None
        what = str(side)
    else:
        what = "--spacing"
    if spacing is not None:
        if src.transform is not None:
            raise IngestError(f"{p}: has its own georeference (spacing {src.spacing()[0]:g} x {src.spacing()[1]:g}); "
                              "--spacing is for inputs without one")
        dx, dy = parse_spacing(spacing, what)
        src.transform = (0.0, dx, 0.0, 0.0, 0.0, -dy)
        src.anchored = False
    if crs is not None:
        if src.crs is not None:
            raise IngestError(f"{p}: has its own CRS ({crs_name(src.crs)}); --crs is for inputs without one")
        src.crs = _crs_wkt(crs, "--crs")


def open_source(path, *, nodata=None, array: str | None = None, shape: tuple[int, int] | None = None,
                dtype: str | None = None, spacing=None, crs: str | None = None) -> RasterSource:
    """Open an elevation input by its extension (see module docstring). ``spacing`` (``DX`` or
    ``DX,DY``) and ``crs`` georeference an input that has none."""
    p = Path(path)
    if not p.exists():
        raise IngestError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if suffix in (".tif", ".tiff", ".gtiff", ".vrt", ".img", ".asc"):
        src = GeoTiffSource(p)
    elif suffix == ".npy":
        src = _npy_source(p)
    elif suffix == ".hgt":
        src = HgtSource(p)
    elif suffix == ".npz":
        try:
            with np.load(p) as z:
                names = list(z.keys())
                if array is None:
                    if len(names) != 1:
                        raise IngestError(f"{p}: holds arrays {', '.join(names)}; name one with --array")
                    array = names[0]
                if array not in names:
                    raise IngestError(f"{p}: has no array {array!r} (it holds {', '.join(names)})")
                src = ArraySource(z[array], f"{p.name}:{array}")
        except (zipfile.BadZipFile, OSError, ValueError) as e:
            raise IngestError(f"{p}: not a readable .npz file ({e})") from None
    elif suffix in (".raw", ".bin", ".r32", ".f32", ".r16", ".dat"):
        if shape is None or dtype is None:
            raise IngestError(f"{p}: raw binary needs --shape ROWSxCOLS and --dtype (e.g. float32, <i2)")
        try:
            itemsize = np.dtype(dtype).itemsize
        except TypeError:
            raise IngestError(f"--dtype {dtype!r}: not a data type; give one such as float32, int16, <i2 or >u2") from None
        want = shape[0] * shape[1] * itemsize
        if p.stat().st_size != want:
            raise IngestError(f"{p}: is {p.stat().st_size} bytes, but --shape {shape[0]}x{shape[1]} --dtype {dtype} needs {want}")
        src = BinaryFileSource(p, shape, dtype, 0, p.name)
    else:  # any other raster GDAL reads (ESRI .bil/.flt, NetCDF, a zipped SRTM tile, ...), else a list of what works
        try:
            src = GeoTiffSource(p)
        except IngestError:
            raise IngestError(f"{p}: unknown input format {suffix or '(no extension)'}; use a raster GDAL reads (.tif/.tiff, "
                              ".vrt, .img, .asc, .bil, .flt, .nc, .hgt or .hgt.zip named like N45E006), .npy, .npz (--array), or "
                              "raw (.raw/.bin/.r32/.f32/.r16/.dat with --shape and --dtype); or convert it: gdal_translate -of "
                              "GTiff IN OUT.tif") from None
    if nodata is not None:
        src.nodata = nodata
    _georeference(src, p, spacing, crs)
    st = p.stat()
    src.stamp = [st.st_size, st.st_mtime_ns]
    return src


@dataclass(frozen=True)
class OrthoPlacement:
    """Which orthophoto pixel colours each DEM sample: image row ``floor(sy·r + ty)`` and column
    ``floor(sx·c + tx)`` of DEM sample (r, c), clamped to the image (samples outside it take the
    nearest edge pixel). ``georeferenced``: placed by both rasters' transforms; otherwise the
    image is stretched over the DEM's extent. ``note``: what ``prepare`` should tell the user."""

    sy: float
    ty: float
    sx: float
    tx: float
    georeferenced: bool
    covered: float = 1.0
    note: str | None = None

    @classmethod
    def stretched(cls, dem_rows: int, dem_cols: int, ortho: RasterSource, note: str | None = None) -> "OrthoPlacement":
        """The image stretched over the DEM's extent (no georeference used)."""
        return cls(ortho.rows / dem_rows, 0.0, ortho.cols / dem_cols, 0.0, False, note=note)


def _north_up(t) -> bool:
    return t is not None and t[2] == 0 and t[4] == 0 and t[1] != 0 and t[5] != 0


def _bounds(src: RasterSource) -> str:
    c, a, _, f, _, e = src.transform
    xs, ys = sorted((c, c + a * src.cols)), sorted((f, f + e * src.rows))
    return f"x {xs[0]:.10g}..{xs[1]:.10g}, y {ys[0]:.10g}..{ys[1]:.10g}"


def _same_crs(a: str, b: str) -> bool:
    try:
        from rasterio.crs import CRS

        return CRS.from_user_input(a) == CRS.from_user_input(b)
    except Exception:  # noqa: BLE001 - unparsable: compare the text
        return a.strip() == b.strip()


def _axis_cover(s: float, t: float, n: int, size: int) -> float:
    """Fraction of the DEM samples 0..n-1 of one axis whose image index ``s·i + t`` lies in [0, size)."""
    idx = np.floor(s * np.arange(n) + t)
    return float(np.count_nonzero((idx >= 0) & (idx < size))) / n


def place_ortho(dem: RasterSource, ortho: RasterSource) -> OrthoPlacement:
    """How ``ortho`` colours ``dem`` (see :class:`OrthoPlacement`). Where both rasters carry a
    georeference from their files (north-up transforms, the same CRS), the image is placed by
    it: an image of another place is an error, one covering part of the DEM a note. Otherwise
    (either has none, or only a ``--spacing``) the image is stretched over the DEM, as before."""
    dem_geo = dem.transform is not None and dem.anchored
    ortho_geo = ortho.transform is not None and ortho.anchored
    if not (dem_geo and ortho_geo):
        note = None
        if dem_geo != ortho_geo:
            which, other = (ortho, dem) if ortho_geo else (dem, ortho)
            note = (f"{other.name} has no georeference, so {ortho.name} is stretched over the DEM's extent "
                    f"({which.name}'s georeference is not used)")
        return OrthoPlacement.stretched(dem.rows, dem.cols, ortho, note)
    if dem.crs and ortho.crs and not _same_crs(dem.crs, ortho.crs):
        raise IngestError(f"--color {ortho.name}: its CRS ({crs_name(ortho.crs)}) differs from the DEM's ({crs_name(dem.crs)}); "
                          "reproject it to the DEM's CRS first (e.g. gdalwarp -t_srs)")
    if not (_north_up(dem.transform) and _north_up(ortho.transform)):
        raise IngestError(f"--color {ortho.name}: a rotated or sheared georeference is not supported; warp the image and the DEM "
                          "to north-up grids first (e.g. gdalwarp)")
    c, a, _, f, _, e = dem.transform
    oc, oa, _, of, _, oe = ortho.transform
    sy, ty, sx, tx = e / oe, (f - of) / oe, a / oa, (c - oc) / oa
    cover = _axis_cover(sy, ty, dem.rows, ortho.rows) * _axis_cover(sx, tx, dem.cols, ortho.cols)
    if cover == 0:
        raise IngestError(f"--color {ortho.name} does not cover the DEM {dem.name}: the image spans {_bounds(ortho)}, the DEM "
                          f"{_bounds(dem)}; give an orthophoto of the same area")
    note = None
    if cover < 0.999:
        note = (f"{ortho.name} covers {cover:.0%} of the DEM {dem.name} (image {_bounds(ortho)}, DEM {_bounds(dem)}); "
                "samples outside it take the colour of the image's nearest edge pixel")
    return OrthoPlacement(sy, ty, sx, tx, True, cover, note)
