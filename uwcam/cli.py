"""The ``uwcam`` command line: calibrate, range, simulate, run, config check."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from uwcam import __version__
from uwcam.drivers.base import DriverError
from uwcam.fileio import UserInputError
from uwcam.commands.calibrate import cmd_calibrate, cmd_response, cmd_rig_print
from uwcam.commands.daemon import cmd_config_check, cmd_run, cmd_warmup
from uwcam.commands.monitor import cmd_monitor
from uwcam.commands.ranging import cmd_range, cmd_simulate
from uwcam.commands.recordings import cmd_repair, cmd_reprocess


def add_channels_and_lamp(parser: argparse.ArgumentParser, channels: str, channels_help: str, lamp_help: str) -> None:
    """--channels (its form ``channels``) and --lamp-offset, alike in `uwcam calibrate` and `uwcam simulate`."""
    parser.add_argument("--channels", metavar=channels, help=channels_help)
    parser.add_argument("--lamp-offset", metavar="X,Y,Z", help=f"lamp position in metres, camera frame {lamp_help}")


def add_exposure(parser: argparse.ArgumentParser, whose: str, prefix: str = "--") -> None:
    """--exposure-us and --gain-db (after ``prefix``): per channel, as docs/exposure.md describes."""
    parser.add_argument(f"{prefix}exposure-us", metavar="T|T1,T2,..|R=T1,..",
                        help=f"{whose} exposure time in µs: one for all channels, one per channel, or by channel name")
    parser.add_argument(f"{prefix}gain-db", metavar="G|G1,G2,..|R=G1,..",
                        help=f"{whose} analogue gain in dB, given with the exposure time, in the same forms")


def add_command(sub: argparse._SubParsersAction, name: str, summary: str,
                description: str | None = None) -> argparse.ArgumentParser:
    """A subcommand: ``summary`` is its line in the parent's ``--help``, ``description`` (default:
    ``summary`` as a sentence) opens its own ``--help``."""
    return sub.add_parser(name, help=summary, description=description or f"{summary[0].upper()}{summary[1:]}.")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="uwcam", description="Underwater ranging camera: calibrate, range, simulate, run.")
    parser.add_argument("--version", action="version", version=f"uwcam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    cal = add_command(sub, "calibrate", "make a calibration profile from a target imaged at known distances")
    cal.add_argument("images", nargs="+", metavar="IMAGE",
                     help="target images (.npy, .tif, .png), one per --distance; several at one distance are averaged")
    cal.add_argument("--distance", type=float, action="append", metavar="D",
                     help="camera-to-target distance along the optical axis in metres, one per image in order "
                          "(repeat a distance for several frames taken there)")
    cal.add_argument("--target-reflectance", metavar="R1,R2,...", help="target reflectance per channel (default: spectrally flat)")
    cal.add_argument("--rig", metavar="RIG.yaml", help="rig file describing the target (calibration_rigs/)")
    cal.add_argument("--roi", metavar="X,Y,W,H", help="target region in pixels (default: the whole image)")
    cal.add_argument("--black-roi", metavar="X,Y,W,H", help="black patch region in pixels, for the noise floor")
    add_channels_and_lamp(cal, "NAME[:NM],...", "channel names, optionally with centre wavelengths (R:675,G:575,B:475)",
                          "(x right, y down, z forward)")
    cal.add_argument("--reference", metavar="NAME", help="reference channel (default: the first)")
    cal.add_argument("--lamp-radius", type=float, metavar="R",
                     help="effective lamp radius sqrt(A0/Ω) in metres (0: point source); enables absolute attenuation")
    cal.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="pinhole intrinsics in pixels")
    cal.add_argument("--dark", metavar="IMAGE", help="dark frame (lamp off, lens capped) to subtract")
    cal.add_argument("--dark-level", metavar="D1,D2,...", help="dark level per channel in DN to subtract")
    cal.add_argument("--saturation", type=float, metavar="DN", help="raw level at which pixels clip (default: the dtype's maximum)")
    cal.add_argument("--name", help="name stored in the profile (default: the file's stem)")
    cal.add_argument("-o", "--output", required=True, metavar="PROFILE.yaml", help="profile to write")
    cal.add_argument("--report", metavar="REPORT.html",
                     help="also write a self-contained HTML report: fits, residuals, noise model, plate overlay, range σ")
    cal.add_argument("--response", metavar="srgb|rec709|FILE",
                     help="the camera's response curve (a gamma-encoded 8-bit camera): frames are linearised "
                          "through it and the profile keeps it; FILE from 'uwcam response'")
    cal.add_argument("--flat-field", nargs="+", metavar="IMAGE",
                     help="frames of an evenly lit view (a diffuser over the port, a white target filling the view, "
                          "lamp or daylight even across it): the lens's shading (vignetting) is measured from them "
                          "and kept in the profile (needs --intrinsics)")
    add_exposure(cal, "the calibration frames' (all alike; recorded in the profile)")
    cal.set_defaults(func=cmd_calibrate)

    resp = add_command(sub, "response", "recover an 8-bit camera's response curve from an exposure bracket")
    resp.add_argument("images", nargs="+", metavar="BRACKET",
                      help="8-bit frames of one still, lit scene at different exposures (fixed gain and white balance)")
    resp.add_argument("--exposure-ms", required=True, metavar="T1,T2,...", help="exposure of each frame in ms, in order")
    resp.add_argument("--method", choices=("debevec", "robertson"), default="debevec",
                      help="OpenCV's calibration method (default debevec)")
    resp.add_argument("-o", "--output", required=True, metavar="RESPONSE.yaml",
                      help="response file, for 'uwcam calibrate --response'")
    resp.set_defaults(func=cmd_response)

    rig = add_command(sub, "rig", "calibration rig tools")
    rig_sub = rig.add_subparsers(dest="rig_command", required=True, metavar="ACTION")
    rig_print = add_command(rig_sub, "print", "draw a rig's plate (markers, target, black patch) at true scale as PDF")
    rig_print.add_argument("rig", metavar="RIG", help="rig file or built-in rig name (e.g. charuco-plate)")
    rig_print.add_argument("-o", "--output", required=True, metavar="BOARD.pdf")
    rig_print.set_defaults(func=cmd_rig_print)

    rng = add_command(sub, "range", "turn an image into a range map with a calibration profile")
    rng.add_argument("profile", metavar="PROFILE.yaml",
                     help="calibration profile of this camera, lamp and water (from 'uwcam calibrate' or the daemon)")
    rng.add_argument("image", metavar="IMAGE", nargs="+",
                     help="image to range; several of one static scene are fused first (their mean, noise from their count)")
    rng.add_argument("-o", "--output", required=True, metavar="RANGE.(npy|tif)", help="float32 camera range in metres, NaN invalid")
    rng.add_argument("--variance", metavar="VAR.(npy|tif)", help="variance of the range in m²")
    rng.add_argument("--reasons", metavar="REASONS.(npy|tif)", help="uint8 reason code per pixel (0 valid)")
    rng.add_argument("--surface-reflectance", metavar="R1,R2,...", help="surface reflectance per channel, if it differs in hue from the target")
    rng.add_argument("--pair", metavar="NAME,NAME", help="use one channel pair instead of fusing all channels")
    rng.add_argument("--path-bounds", metavar="MIN,MAX", help="accepted lamp→surface→camera path length in metres")
    rng.add_argument("--smoothing", "--smooth", dest="smooth", choices=("none", "mean", "median", "adaptive"),
                     help="3×3 smoothing of the range map over valid pixels (mean, median), or windows that adapt "
                     "to the signal (adaptive: up to 17×17 where σ is above --smoothing-target)")
    rng.add_argument("--smoothing-target", metavar="FRACTION",
                     help="adaptive smoothing's target σ as a fraction of the range, 0.001–0.5 (default 0.02: 2 %%)")
    rng.add_argument("--compensate-backscatter", action="store_true",
                     help="insist on subtracting modelled backscatter (done anyway whenever the profile was calibrated "
                     "with a black patch; with this flag a profile without one is refused)")
    rng.add_argument("--open-water", metavar="IMAGE", nargs="+", action="extend",
                     help="lamp-lit frame(s) of open water (after the images, or the flag repeated): the backscatter "
                     "pattern, and the light each pixel must be clearly above to have a range; several are averaged "
                     "as the daemon's capture is, which also finds each pixel's response")
    add_exposure(rng, "the images'")
    add_exposure(rng, "the open-water frames'", "--open-water-")
    rng.set_defaults(func=cmd_range)

    sim = add_command(sub, "simulate", "render a physically modelled underwater frame (and its ground truth)")
    sim.add_argument("--list", action="store_true", help="list scenes and water presets")
    sim.add_argument("--scene", metavar="NAME", help="seabed, brick, pipe, ball, ring, tilted-plane, plate or open-water")
    sim.add_argument("--range", type=float, metavar="METRES", help="camera-to-seabed (or plate) distance along the optical axis")
    sim.add_argument("--water", default="jerlov-II", metavar="PRESET", help="water preset (default jerlov-II; see --list)")
    sim.add_argument("--attenuation", metavar="C[,C,...]", help="override beam attenuation c, 1/m")
    sim.add_argument("--forward-blur", type=float, metavar="B", help="forward-scatter blur B (OTF exp(−B·d·f))")
    sim.add_argument("--scatter-attenuation", metavar="G[,G,...]", help="attenuation of forward-scattered light G, 1/m")
    sim.add_argument("--backscatter", metavar="BETA[,BETA,...]", help="backscatter β, 1/(m·sr)")
    sim.add_argument("--gated", action="store_true", help="range gating: only water just in front of the surface scatters back")
    sim.add_argument("--gate-width", type=float, default=0.05, metavar="M", help="depth of the range gate (default 0.05 m)")
    sim.add_argument("--slabs", type=int, default=32, help="water-column slabs for backscatter (default 32)")
    sim.add_argument("--bits", type=int, default=16, choices=(8, 12, 16), help="sensor bit depth (default 16)")
    sim.add_argument("--response", default="linear", choices=("linear", "srgb", "rec709"),
                     help="tone curve of the camera's 8-bit output (default linear); needs --bits 8")
    sim.add_argument("--jpeg-quality", type=int, metavar="Q",
                     help="JPEG-compress the frame at quality Q (1–100), as an MJPEG camera does; needs --bits 8")
    sim.add_argument("--size", default="640x480", metavar="WxH", help="image size (default 640x480)")
    sim.add_argument("--fov", type=float, default=60.0, metavar="DEG", help="horizontal field of view (default 60)")
    add_channels_and_lamp(sim, "NAME:NM,...", "channel names and centre wavelengths (default R:675,G:575,B:475)", "(default at the camera)")
    sim.add_argument("--lamp-off", action="store_true", help="lamp off: dark current, noise and any ambient light only")
    sim.add_argument("--ambient", metavar="I[,I,...]", help="daylight from above, relative to the lamp")
    sim.add_argument("--peak", type=float, metavar="DN",
                     help="auto-exposure target for the brightest pixel (default 226 at 8 bits, 4077 at 12, 65250 at 16)")
    sim.add_argument("--exposure", type=float, help="fix the exposure (electrons per unit radiance) instead of auto-exposure")
    sim.add_argument("--rig", metavar="RIG", help="rig file or built-in rig name for --scene plate (default grey-plate)")
    sim.add_argument("--material", metavar="NAME", help="give every surface one material (sand, brick, pipe, ball, ring, grey)")
    sim.add_argument("--noise-free", action="store_true", help="write the expected value (float32 DN) without noise")
    sim.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    sim.add_argument("-o", "--output", metavar="FRAME.(tif|npy|png)")
    sim.add_argument("--truth", metavar="TRUTH.npy", help="write camera range per pixel (m, NaN where no surface)")
    sim.set_defaults(func=cmd_simulate)

    run = add_command(sub, "run", "run the camera daemon (default: simulated rig, API on 127.0.0.1:8080)",
                      "Run the camera daemon: open the camera, lamp and rangefinder of the configuration (default: "
                      "the embedded simulated rig), range every frame, and serve the operator page and the API "
                      "(default http://127.0.0.1:8080/, the API's reference at /docs). Ctrl-C or SIGTERM stops it "
                      "and switches the lamp off. 'uwcam config check FILE' validates a configuration without "
                      "starting anything.")
    run.add_argument("--config", metavar="FILE", help="rig configuration (YAML); default: the embedded simulated rig")
    run.add_argument("--simulate", choices=("vehicle", "tank"),
                     help="run an embedded simulation: vehicle (the default: a survey over a varied seabed) or tank "
                          "(a calibration plate on a rail, moved with PUT /api/v1/simulation/plate)")
    run.add_argument("--host", help="API address (default 127.0.0.1)")
    run.add_argument("--port", type=int, help="API port (default 8080)")
    run.add_argument("--record", metavar="FILE.mcap", help="record the dive into this MCAP file from start to stop")
    run.set_defaults(func=cmd_run)

    mon = add_command(sub, "monitor", "topside fleet view: every vehicle publishing on Zenoh, on one page")
    mon.add_argument("--connect", nargs="+", default=[], metavar="ENDPOINT",
                     help="Zenoh endpoints of the vehicles (or of a router), e.g. tcp/192.168.2.2:7447")
    mon.add_argument("--listen", nargs="+", default=[], metavar="ENDPOINT",
                     help="Zenoh endpoints to listen on, for vehicles that connect to the monitor")
    mon.add_argument("--no-scouting", dest="scouting", action="store_false",
                     help="do not look for vehicles on the LAN by multicast (only --connect and --listen)")
    mon.add_argument("--host", default="127.0.0.1", help="address of the fleet page (default 127.0.0.1)")
    mon.add_argument("--port", type=int, default=8090, help="port of the fleet page (default 8090)")
    mon.add_argument("--stale-s", type=float, default=5.0, metavar="S",
                     help="a vehicle unheard for S seconds is shown stale (default 5)")
    mon.add_argument("--root", default="uwcam", help="key root the vehicles publish under (default uwcam)")
    mon.set_defaults(func=cmd_monitor)

    warm = add_command(sub, "warmup", "compile the ranging and simulation kernels now, so that no later start "
                                      "compiles any ('bash deploy/install.sh test' runs it; 'uwcam run' starts it in "
                                      "the background, once per install)")
    warm.add_argument("--timeout", type=float, default=600.0, metavar="S", help="give up after S seconds (default 600)")
    warm.add_argument("--profile", metavar="PROFILE.yaml",
                      help="only the ranging kernels, for this calibration profile's channels (uwcam run starts this "
                           "in the background when the cache lacks them)")
    warm.add_argument("--processing", metavar="SETTINGS.json",
                      help="with --profile: processing settings (as GET /api/v1/config gives them) whose kernels come first")
    warm.set_defaults(func=cmd_warmup)

    rep = add_command(sub, "reprocess", "range recorded dives (MCAP) again, here or on a Dask cluster")
    rep.add_argument("inputs", nargs="+", metavar="IN.mcap", help="recordings made by uwcam run")
    rep.add_argument("-o", "--output", required=True, metavar="OUT",
                     help="output .mcap for one input, else a folder (one file per input, same names)")
    rep.add_argument("--profile", metavar="P.yaml", help="calibration profile to use (default: the one recorded in each file)")
    rep.add_argument("--scheduler", nargs="?", const="local", metavar="ADDRESS",
                     help="run on a Dask cluster: a scheduler address (tcp://host:8786; workers must see the same "
                          "paths), or without ADDRESS a local cluster on this machine (default: in this process)")
    rep.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster (default: CPU count)")
    rep.add_argument("--part-mb", type=float, default=64.0, metavar="MB",
                     help="megabytes of recording per unit of work, cut at MCAP chunks (default 64)")
    rep.add_argument("--quiet", action="store_true", help="no progress bar")
    rep.add_argument("--skip-corrupt", action="store_true",
                     help="reprocess a recording with damaged chunks (failing their CRC check), leaving them out; "
                          "without it such a recording is refused")
    rep.set_defaults(func=cmd_reprocess)

    fix = add_command(sub, "repair", "make unfinished recordings (writer killed, disk full) readable, in place")
    fix.add_argument("recordings", nargs="+", metavar="FILE.mcap",
                     help="recordings made by uwcam run; complete ones are left as they are")
    fix.set_defaults(func=cmd_repair)

    cfg = add_command(sub, "config", "configuration tools")
    cfg_sub = cfg.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    check = add_command(cfg_sub, "check", "validate a configuration file without starting anything")
    check.add_argument("file", metavar="FILE", help="rig configuration (YAML), as given to 'uwcam run --config'")
    check.set_defaults(func=cmd_config_check)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (UserInputError, DriverError) as exc:  # a device's own errors say what happened and what to do
        print(f"uwcam {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
