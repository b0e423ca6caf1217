"""`crepuscular-usd`: render light-shaft layers from a USD stage, or author the schema.

    crepuscular-usd render STAGE --camera /cam --frames 1-100x2 --out 'shafts.####.exr'
        [--light /sun] [--renderSettingsPrimPath /Render/settings]
        [--beauty 'beauty.####.exr' [--comp 'comp.####.exr']]
        [--out-layer shafts.usda] [--width W] [--height H] [--half]
        [--exr-compression zip|zips|piz|rle|none|pxr24] [--quiet]
    crepuscular-usd apply-schema STAGE --light /sun [--medium-extent /fog] [--output FILE]

Exit status: 0 on success, 2 for command-line errors (a bad frame range or frame
placeholder included), 1 when the stage, its camera or light, an input file or a render
fails. Every error is one line on stderr that names what is wrong.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import TextIO

import numpy as np
import numpy.typing as npt
from pxr import Sdf, Tf, Usd, UsdGeom

import crepuscular
from crepuscular_usd import __version__
from crepuscular_usd.attributes import HOLES_OBJECTS
from crepuscular_usd.frames import FrameSpecError, add_cmdline_args, validate_cmdline_args
from crepuscular_usd.geometry import MeshError
from crepuscular_usd.output import OutputLayerError, RenderRecord, write_output_layer
from crepuscular_usd.render_settings import RenderSettingsError, read_render_settings
from crepuscular_usd.schema import API_NAME, SchemaError, apply_schema
from crepuscular_usd.stage import StageError, StageReader, open_stage, tf_message

__all__ = ["main"]

PROG = "crepuscular-usd"


class CommandError(Exception):
    """A failure that ends the command with a message and exit status 1."""


class UsageError(Exception):
    """A command-line mistake: exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(message)


#: usdrecord's complexities, as the levels Hydra refines subdivision meshes at each.
COMPLEXITY_LEVELS = {"low": 0, "medium": 1, "high": 2, "veryhigh": 3}


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    render = commands.add_parser("render", help="render layer EXRs for a frame range")
    render.add_argument("stage", metavar="STAGE", help="the USD stage to render")
    render.add_argument(
        "--camera",
        "-cam",
        help="camera prim path (default: the render settings' camera, else the only camera)",
    )
    render.add_argument(
        "--light", help="DistantLight prim path (default: the only one, preferring the API)"
    )
    render.add_argument(
        "--renderSettingsPrimPath",
        "-rs",
        dest="render_settings",
        help=(
            "RenderSettings prim whose camera, resolution, pixel aspect, aperture conform "
            "policy and included purposes to render with (default: the stage's "
            "renderSettingsPrimPath, else its only RenderSettings prim)"
        ),
    )
    render.add_argument(
        "--renderProduct",
        dest="render_product",
        help=(
            "RenderProduct whose authored camera, resolution, pixel aspect, conform policy "
            "and data window override the settings' (default: the settings' only product, "
            "else their first)"
        ),
    )
    add_cmdline_args(render)
    render.add_argument(
        "--out", required=True, help="layer EXR path with a frame placeholder, e.g. shafts.####.exr"
    )
    render.add_argument(
        "--beauty", help="beauty EXR sequence to composite over, e.g. beauty.####.exr"
    )
    render.add_argument(
        "--comp", help="composited EXR path (default: 'comp.' + the --out file name, same folder)"
    )
    render.add_argument(
        "--beauty-depth",
        choices=("auto", "planar", "ray_distance", "ignore"),
        default="auto",
        help=(
            "how the beauty's depth channel measures distance, in stage units: auto takes "
            "our own 'depth' as ray distance and any other (Depth.Z, Z) as planar"
        ),
    )
    render.add_argument("--out-layer", help="USD layer recording the products and settings")
    render.add_argument(
        "--width",
        type=int,
        help="image width (default: the render settings', else the beauty's, else 1920)",
    )
    render.add_argument(
        "--height",
        type=int,
        help=(
            "image height (default: the render settings', else the beauty's, else from "
            "the aperture)"
        ),
    )
    render.add_argument(
        "--complexity",
        "-c",
        choices=tuple(COMPLEXITY_LEVELS),
        default="low",
        help=(
            "how finely to draw Catmull-Clark meshes, as usdrecord's: low casts their "
            "control cages (Storm's default), medium, high and veryhigh refine them 1, 2 "
            "and 3 levels onto their limit surface. Meshes that author "
            "crepuscular:subdivision:levels (Blender's export) keep their own"
        ),
    )
    render.add_argument("--half", action="store_true", help="write volume and visibility as half")
    render.add_argument(
        "--exr-compression",
        choices=crepuscular.EXR_COMPRESSIONS,
        default="zip",
        help=(
            "EXR codec of the layers and composites: zip (default), zips, piz (faster to "
            "write, slower to read), rle, none, or pxr24 (lossy: floats rounded to 24 bits)"
        ),
    )
    render.add_argument("--quiet", "-q", action="store_true", help="no progress bar")

    schema = commands.add_parser("apply-schema", help=f"apply {API_NAME} with its defaults")
    schema.add_argument("stage", metavar="STAGE", help="the USD stage (or layer) to edit")
    schema.add_argument("--light", required=True, help="DistantLight prim path")
    schema.add_argument("--medium-extent", help="prim whose bounds make the medium's box")
    schema.add_argument("--output", "-o", help="write the edited stage here (default: in place)")
    return parser


# --- progress ---------------------------------------------------------------------------


class Progress:
    """A plain-text progress bar on stderr: one line redrawn on a terminal, else per frame."""

    WIDTH = 30

    def __init__(self, total: int, stream: TextIO, enabled: bool) -> None:
        self.total = total
        self.stream = stream
        self.enabled = enabled
        self.tty = stream.isatty()
        self.started = time.perf_counter()
        self._last = -1.0

    def update(self, done_frames: int, fraction: float, label: str) -> None:
        if not self.enabled:
            return
        overall = (done_frames + fraction) / self.total
        if not self.tty and fraction not in (0.0, 1.0):
            return
        if self.tty and overall - self._last < 0.005 and fraction not in (0.0, 1.0):
            return
        self._last = overall
        filled = int(self.WIDTH * overall)
        bar = "#" * filled + "-" * (self.WIDTH - filled)
        elapsed = time.perf_counter() - self.started
        line = f"[{bar}] {overall * 100:5.1f}% {label} ({elapsed:.1f} s)"
        if self.tty:
            self.stream.write("\r" + line)
        elif fraction == 1.0:
            self.stream.write(line + "\n")
        self.stream.flush()

    def finish(self) -> None:
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()


# --- beauty -----------------------------------------------------------------------------


def _check_beauty_pixels(path: str, pixel_aspect: float, err: TextIO) -> None:
    """Warns where the first beauty's pixels are not the camera's shape: a beauty
    rendered through other pixels sees another view, and the shafts would not line up."""
    beauty_aspect = crepuscular.read_exr_pixel_aspect(path)
    if not math.isclose(beauty_aspect, pixel_aspect, rel_tol=1e-3):
        _warn(
            err,
            f"beauty {path} has pixels {beauty_aspect:g}:1 (its pixelAspectRatio) but the "
            f"camera renders {pixel_aspect:g}:1: the shafts may not line up (see the render "
            "settings' pixelAspectRatio)",
        )


def _beauty_planes(
    path: str, width: int, height: int
) -> tuple[npt.NDArray[np.float32], tuple[str, npt.NDArray[np.float32]] | None]:
    """RGBA (H, W, 4) and, if present, the (channel, plane) depth pass of a beauty EXR."""
    try:
        channels = crepuscular.read_exr(path)
    except (OSError, crepuscular.CrepuscularError) as error:
        raise CommandError(f"cannot read beauty {path}: {error}") from error
    # Blender's multi-layer files: the first view layer's Combined pass, else plain RGBA.
    combined = sorted(n for n in channels if n == "Combined.R" or n.endswith(".Combined.R"))
    prefix = combined[0][: -len("R")] if combined else None
    if prefix is None and "R" in channels:
        prefix = ""
    if prefix is None or any(f"{prefix}{c}" not in channels for c in "GB"):
        raise CommandError(
            f"beauty {path} has no R, G, B channels (nor a render layer's Combined.R/G/B)"
        )
    first = channels[f"{prefix}R"]
    if first.shape != (height, width):
        raise CommandError(
            f"beauty {path} is {first.shape[1]}x{first.shape[0]} but the camera renders "
            f"{width}x{height}; pass --width/--height to match"
        )
    alpha = channels.get(f"{prefix}A", np.ones_like(first))
    rgba = np.stack([channels[f"{prefix}{c}"] for c in "RGB"] + [alpha], axis=-1)
    depth_name = next((n for n in sorted(channels) if n.endswith(".Depth.Z")), None)
    for candidate in ("depth.Z", "depth", "Z"):
        if depth_name is None and candidate in channels:
            depth_name = candidate
    depth = (depth_name, channels[depth_name]) if depth_name is not None else None
    return rgba.astype(np.float32), depth


def _beauty_size(path: str) -> tuple[int, int]:
    if not os.path.isfile(path):
        raise CommandError(f"beauty {path} does not exist")
    try:
        channels = crepuscular.read_exr(path)
    except (OSError, crepuscular.CrepuscularError) as error:
        raise CommandError(f"cannot read beauty {path}: {error}") from error
    if not channels:
        raise CommandError(f"beauty {path} has no channels")
    height, width = next(iter(channels.values())).shape
    return int(width), int(height)


# --- commands ---------------------------------------------------------------------------


def _frame_path(template: str, time_code: Usd.TimeCode) -> str:
    if time_code.IsDefault() or time_code.IsEarliestTime():
        return template
    return template.format(frame=time_code.GetValue())


def _resolve_time(stage: Usd.Stage, time_code: Usd.TimeCode) -> Usd.TimeCode:
    # usdrecord works at the earliest time without --frames; name it for file records.
    if time_code.IsEarliestTime():
        if stage.HasAuthoredTimeCodeRange():
            return Usd.TimeCode(stage.GetStartTimeCode())
        return Usd.TimeCode.Default()
    return time_code


def _record_key(time_code: Usd.TimeCode) -> float | None:
    return None if time_code.IsDefault() else float(time_code.GetValue())


def _warn(stream: TextIO, message: str) -> None:
    stream.write(f"{PROG}: warning: {message}\n")


@contextmanager
def _naming_frame(label: str, reader: StageReader) -> Iterator[None]:
    """Begins the errors of reading and rendering one frame with `label`: an animated
    attribute may be wrong at one frame of a hundred. The renderer's range checks are
    named by the attribute that fed them (`StageReader.source_of`)."""
    try:
        yield
    except crepuscular.InvalidInputError as error:
        field = getattr(error, "field", None)
        source = reader.source_of(field) if field else None
        if source:
            where = f"{source}: "
        else:
            where = f"the renderer rejected the frame{f' ({field})' if field else ''}: "
        raise CommandError(f"{label}: {where}{error}") from error
    except (StageError, SchemaError, MeshError, crepuscular.CrepuscularError) as error:
        raise CommandError(f"{label}: {error}") from error
    except Tf.ErrorException as error:
        raise CommandError(f"{label}: USD: {tf_message(error)}") from error


def _render(args: argparse.Namespace, err: TextIO) -> int:
    if args.comp and not args.beauty:
        raise UsageError("--comp needs --beauty")
    for name in ("width", "height"):
        value = getattr(args, name)
        if value is not None and not 1 <= value <= 16384:
            raise UsageError(f"--{name} {value} is outside 1..16384")
    if args.beauty and not args.comp:
        folder, name = os.path.split(args.out)
        args.comp = os.path.join(folder, "comp." + name)
    paths = [os.path.abspath(p) for p in (args.out, args.beauty, args.comp) if p]
    if len(set(paths)) != len(paths):
        raise UsageError("--out, --beauty and --comp must be different paths")
    try:
        frame_args = validate_cmdline_args(args, ("out", "beauty", "comp"))
    except FrameSpecError as error:
        raise UsageError(str(error)) from error
    if not os.path.isfile(args.stage):
        raise CommandError(f"cannot open stage {args.stage}: no such file")
    stage = open_stage(args.stage)
    for option in ("out", "comp", "out_layer"):
        _make_folder(getattr(args, option), option)
    time_codes = [_resolve_time(stage, code) for code in frame_args.time_codes]
    try:
        image = read_render_settings(stage, args.render_settings, args.render_product)
    except RenderSettingsError as error:
        raise CommandError(str(error)) from error
    for note in image.notes:
        _warn(err, note)
    width, height = args.width, args.height
    if image.resolution is not None:
        # One side given scales the settings' image.
        full_width, full_height = image.resolution
        if width is None and height is None:
            width, height = full_width, full_height
        elif width is None:
            width = max(1, round(height * full_width / full_height))
        elif height is None:
            height = max(1, round(width * full_height / full_width))
    elif args.beauty and width is None and height is None:
        width, height = _beauty_size(_frame_path(frame_args.formats["beauty"], time_codes[0]))
    reader = StageReader(
        stage,
        args.camera,
        args.light,
        width=width,
        height=height,
        image=image,
        subdivision_levels=COMPLEXITY_LEVELS[args.complexity],
    )
    if not reader.light_prim.HasAPI(API_NAME):
        _warn(
            err,
            f"{reader.light_prim.GetPath()} has no {API_NAME}: rendering with the physically "
            "based defaults (run apply-schema to author them)",
        )
    record = RenderRecord(
        camera_path=reader.camera_prim.GetPath(),
        light_path=reader.light_prim.GetPath(),
        stage_path=os.path.abspath(args.stage),
        resolution=(0, 0),
        meters_per_unit=reader.meters_per_unit,
        up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        time_codes_per_second=reader.time_codes_per_second,
        inputs={
            key: getattr(args, key)
            for key in (
                "camera",
                "light",
                "render_settings",
                "render_product",
                "frames",
                "out",
                "beauty",
                "comp",
                "beauty_depth",
                "half",
                "exr_compression",
            )
        },
    )
    progress = Progress(len(time_codes), err, enabled=not args.quiet)
    # Each left-out prim or unmapped material is named once, at the first frame it is.
    named: set[str] = set()
    timings = {"read": 0.0, "render": 0.0}
    loop_started = time.perf_counter()
    writer = _Writer()
    warned_unreached: set[Sdf.Path] = set()
    try:
        for index, time_code in enumerate(time_codes):
            label = "default time" if time_code.IsDefault() else f"frame {time_code.GetValue():g}"
            progress.update(index, 0.0, label)
            started = time.perf_counter()
            with _naming_frame(label, reader):
                frame = reader.read(time_code)
            timings["read"] += time.perf_counter() - started
            invalid = set(frame.geometry.invalid)
            if index == 0:
                skipped = frame.geometry.unsupported
                if skipped or invalid:
                    parts = [f"{count} {kind}" for kind, count in sorted(skipped.items())]
                    parts += [f"{len(invalid)} invalid Mesh"] if invalid else []
                    count = sum(skipped.values()) + len(invalid)
                    _warn(err, f"skipped {count} unsupported prims: {', '.join(parts)}")
            for message in [*sorted(invalid), *frame.geometry.notes]:
                if message not in named:
                    named.add(message)
                    # A prim animated into NaN at one frame would vanish from it unsaid.
                    _warn(err, message if index == 0 else f"{label}: {message}")
            if index == 0:
                disc = frame.sun["angular_diameter"]
                samples = frame.settings["sun_disc_samples"]
                if samples > 1:
                    _warn(
                        err,
                        f"the {math.degrees(disc):.1f}° disc of {reader.light_prim.GetPath()} "
                        f"softens the shafts: {samples} directions over it, each a frame's "
                        "scattering",
                    )
                holes = frame.style.get("holes")
                if holes is not None and not holes["objects"]:
                    roots = ", ".join(str(p) for p in frame.light_settings.holes_roots)
                    _warn(
                        err,
                        f"hole creation is on, but {HOLES_OBJECTS} "
                        + (f"({roots}) holds no rendered mesh" if roots else "names no prim")
                        + ": no holes are made",
                    )
            if len(frame.geometry.triangles) == 0:
                raise CommandError(
                    f"{label}: the stage has no visible mesh triangles to cast shadows"
                )
            kwargs = frame.render_kwargs()
            beauty_rgba = None
            key = _record_key(time_code)
            if args.beauty:
                beauty_path = _frame_path(frame_args.formats["beauty"], time_code)
                if not os.path.isfile(beauty_path):
                    raise CommandError(f"{label}: beauty {beauty_path} does not exist")
                beauty_rgba, depth = _beauty_planes(
                    beauty_path, frame.camera["width"], frame.camera["height"]
                )
                if not record.beauties:
                    _check_beauty_pixels(beauty_path, frame.camera["pixel_aspect"], err)
                if depth is not None and args.beauty_depth != "ignore":
                    name, plane = depth
                    kind = args.beauty_depth
                    if kind == "auto":
                        kind = "ray_distance" if name == "depth" else "planar"
                    window = frame.camera.get("window")
                    if window is not None:
                        rows = slice(window["y"], window["y"] + window["height"])
                        plane = plane[rows, window["x"] : window["x"] + window["width"]]
                    kwargs["camera_depth"] = plane * np.float32(reader.meters_per_unit)
                    kwargs["depth_kind"] = kind
                record.beauties[key] = beauty_path
            started = time.perf_counter()
            with _naming_frame(label, reader):
                layers = crepuscular.render_arrays(
                    **kwargs, progress=lambda f, i=index, lab=label: progress.update(i, f, lab)
                )
            # A data window's layers sit in the whole image, as in a renderer's display
            # window, so that they composite over the beauty.
            layers = layers.in_frame(frame.camera)
            timings["render"] += time.perf_counter() - started
            extent = frame.light_settings.extent_prim
            if (
                extent is not None
                and extent.GetPath() not in warned_unreached
                and crepuscular.fog_box_unreached(kwargs["medium"], layers.volume)
            ):
                warned_unreached.add(extent.GetPath())
                _warn(
                    err,
                    f"{label}: no view ray reaches the fog box {extent.GetPath()}: the frame "
                    "has no fog (is it out of view, behind a surface or past "
                    "crepuscular:maxDistance?)",
                )
            out_path = _frame_path(frame_args.formats["out"], time_code)
            writer.submit(
                lambda p=out_path, lay=layers: crepuscular.write_exr(
                    p, lay, half=args.half, compression=args.exr_compression
                ),
                out_path,
            )
            record.shafts[key] = out_path
            if beauty_rgba is not None:
                comp_path = _frame_path(frame_args.formats["comp"], time_code)
                comp = crepuscular.composite(layers.volume, beauty_rgba)
                planes = {c: comp[..., i] for i, c in enumerate("RGBA")}
                writer.submit(
                    lambda p=comp_path, pl=planes, a=layers.pixel_aspect: (
                        crepuscular.write_exr_channels(
                            p, pl, compression=args.exr_compression, pixel_aspect=a
                        )
                    ),
                    comp_path,
                )
                record.composites[key] = comp_path
            record.resolution = (layers.width, layers.height)
            record.pixel_aspect = frame.camera["pixel_aspect"]
            record.conform = image.conform
            record.settings[key] = frame.settings_record()
    except Exception as error:
        # The frames rendered before the failure are still written: a farm's retry of the
        # range then starts where it failed.
        try:
            writer.close()
        except CommandError as write_error:
            raise CommandError(f"{error}; and {write_error}") from error
        raise
    except BaseException:
        writer.abandon()
        raise
    writer.close()
    progress.finish()
    if args.out_layer:
        write_output_layer(args.out_layer, record)
    if not args.quiet:
        wall = time.perf_counter() - loop_started
        err.write(
            f"{PROG}: {len(time_codes)} frame(s) in {wall:.2f} s: "
            f"read USD {timings['read']:.2f} s, render {timings['render']:.2f} s, "
            f"write {writer.seconds:.2f} s (overlapping the next frame)\n"
        )
    return 0


def _make_folder(path: str | None, option: str) -> None:
    if not path:
        return
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as error:
        flag = "--" + option.replace("_", "-")
        raise CommandError(f"{flag}: cannot create folder {folder}: {error.strerror}") from error


class _Writer:
    """Writes EXRs on one background thread, so that frame N is written while frame N + 1
    renders (both release the GIL). At most one write waits; its error surfaces on the next
    `submit` or on `close`."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="exr-writer")
        self._pending: list[Future[None]] = []
        self.seconds = 0.0

    def _run(self, action: Callable[[], None], path: str) -> None:
        started = time.perf_counter()
        try:
            action()
        except (OSError, crepuscular.CrepuscularError) as error:
            raise CommandError(f"cannot write {path}: {error}") from error
        finally:
            self.seconds += time.perf_counter() - started

    def _drain(self, keep: int) -> None:
        while len(self._pending) > keep:
            self._pending.pop(0).result()

    def submit(self, action: Callable[[], None], path: str) -> None:
        self._drain(keep=1)
        self._pending.append(self._pool.submit(self._run, action, path))

    def abandon(self) -> None:
        """Stops after the write in progress, dropping queued ones and their errors."""
        self._pool.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        try:
            self._drain(keep=0)
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


def _apply_schema(args: argparse.Namespace, err: TextIO) -> int:
    if not os.path.isfile(args.stage):
        raise CommandError(f"cannot open stage {args.stage}: no such file")
    stage = open_stage(args.stage)
    for option, path in (("--light", args.light), ("--medium-extent", args.medium_extent)):
        if path is None:
            continue
        if not Sdf.Path.IsValidPathString(path) or not stage.GetPrimAtPath(path):
            raise CommandError(f"{option} {path} does not exist on the stage")
    extent = Sdf.Path(args.medium_extent) if args.medium_extent else None
    apply_schema(stage.GetPrimAtPath(args.light), medium_extent=extent)
    layer = stage.GetRootLayer()
    saved = layer.Export(args.output) if args.output else layer.Save()
    if not saved:
        raise CommandError(f"cannot save {args.output or args.stage}")
    return 0


def main(argv: Sequence[str] | None = None, *, stderr: TextIO | None = None) -> int:
    """Runs the command line; returns the exit status instead of exiting."""
    err = stderr if stderr is not None else sys.stderr
    try:
        args = _parser().parse_args(argv)
        if args.command == "render":
            return _render(args, err)
        return _apply_schema(args, err)
    except UsageError as error:
        err.write(f"{PROG}: error: {error}\n")
        return 2
    except (
        CommandError,
        StageError,
        SchemaError,
        MeshError,
        OutputLayerError,
        crepuscular.CrepuscularError,
    ) as error:
        err.write(f"{PROG}: error: {error}\n")
        return 1
    except Tf.ErrorException as error:
        err.write(f"{PROG}: error: USD: {tf_message(error)}\n")
        return 1
    except KeyboardInterrupt:
        err.write(f"{PROG}: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())
