"""The viewer's output: draw records into a rerun recording (file, live viewer or both).

Timelines: "mission_time" (duration, the messages' header stamps) and "tick" (the mission clock's
step); rerun's own wall-clock log time is switched off, so a recording converted later reads the
same as the one drawn live. The blueprint opens on: the 3D arena with everything; one tab per UAV
(its own 3D view, its camera's frames, status document and event log); the job managers' states as a state timeline;
every event; plots of detections per second, track uncertainty, CPU and memory per service,
pipeline lag, distance to the nearest partner and the real-time factor.
"""
from __future__ import annotations

import socket
import subprocess
import time

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from services.tools.viz import draw
from services.tools.viz.settings import GRPC_PORT, WEB_PORT, check_viewer, grpc_address, viewer_executable, web_address

APPLICATION_ID = "falconry"
FILL_SOLID, FILL_WIRES = rr.components.FillMode.Solid, rr.components.FillMode.MajorWireframe


def blueprint(uavs: list[str]) -> rrb.Blueprint:
    everything = rrb.Spatial3DView(name="arena", origin="/", contents=["+ /**", "- /plots/**"])
    per_uav = [
        rrb.Vertical(
            rrb.Spatial3DView(name=f"{uav} believes", origin="/",
                              contents=["+ /world/**", "+ /truth/targets/**", f"+ /{uav}/**"]),
            rrb.Horizontal(rrb.Spatial2DView(name=f"{uav} camera", origin=f"/{uav}/camera"),
                           rrb.TextDocumentView(name=f"{uav} status", origin=f"/{uav}/status"),
                           rrb.TextLogView(name=f"{uav} events", origin=f"/{uav}/events")),
            row_shares=[3, 1], name=uav)
        for uav in uavs
    ]
    timelines = rrb.Vertical(
        rrb.StateTimelineView(name="job manager states", origin="/", contents=[f"+ /{u}/state" for u in uavs]),
        rrb.TextLogView(name="events", origin="/events"),
        row_shares=[1, 2])
    plots = rrb.Vertical(
        rrb.TimeSeriesView(name="detections per second, and false ones (truth)", origin="/plots",
                           contents=["+ /plots/detections/**", "+ /plots/false_detections/**",
                                     "+ /plots/camera_detections/**"]),
        rrb.TimeSeriesView(name="track uncertainty radius (m)", origin="/plots/track_uncertainty"),
        rrb.TimeSeriesView(name="CPU per service (%)", origin="/plots/cpu"),
        rrb.TimeSeriesView(name="lag after the scan, worst per second (ms)", origin="/plots/lag_ms"),
        rrb.TimeSeriesView(name="age of the map a scan was classified with (ms)", origin="/plots/map_age_ms"),
        rrb.TimeSeriesView(name="nearest partner (m, truth)", origin="/plots/nearest_partner"),
        rrb.TimeSeriesView(name="memory per service (MB)", origin="/plots/memory_mb"),
        rrb.TimeSeriesView(name="real-time factor", origin="/plots/real_time_factor"),
        name="plots")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(everything, timelines, row_shares=[3, 2]),
            rrb.Tabs(*per_uav, plots, name="per UAV") if per_uav else plots,
            column_shares=[3, 2]),
        rrb.TimePanel(state="expanded", timeline="mission_time"),
        collapse_panels=False,
    )


def archetype(item: draw.Drawable):
    """The rerun archetype that draws one record."""
    match item:
        case draw.Points():
            return rr.Points3D(item.positions, colors=item.colors, radii=item.radius, labels=item.labels,
                               show_labels=item.show_labels)
        case draw.Lines():
            return rr.LineStrips3D(item.strips, colors=item.color, radii=item.radius, labels=item.labels,
                                   show_labels=item.show_labels)
        case draw.Ellipsoids():
            return rr.Ellipsoids3D(centers=item.centers, half_sizes=item.half_sizes, quaternions=item.quaternions,
                                   colors=item.colors, labels=item.labels, show_labels=item.show_labels,
                                   fill_mode=FILL_SOLID if item.solid else FILL_WIRES)
        case draw.Boxes():
            # one half size for all is repeated by rerun for every centre
            return rr.Boxes3D(centers=item.centers, half_sizes=np.asarray(item.half_sizes).reshape(-1, 3),
                              colors=item.colors, labels=item.labels, show_labels=item.show_labels,
                              fill_mode=FILL_SOLID if item.solid else FILL_WIRES)
        case draw.Cylinders():
            return rr.Cylinders3D(centers=item.centers, lengths=item.lengths, radii=item.radii, colors=item.color,
                                  labels=item.labels, show_labels=item.show_labels, fill_mode=FILL_SOLID)
        case draw.Mesh():
            return rr.Mesh3D(vertex_positions=item.vertices, triangle_indices=item.triangles, albedo_factor=item.color)
        case draw.Pose():
            return rr.Transform3D(translation=item.translation, quaternion=rr.Quaternion(xyzw=item.quaternion))
        case draw.Axes():
            return rr.TransformAxes3D(item.length)
        case draw.Text():
            return rr.TextLog(item.text, level=item.level)
        case draw.Image():
            return rr.EncodedImage(contents=item.encoded, media_type=item.media_type)
        case draw.Document():
            return rr.TextDocument(item.markdown, media_type=rr.MediaType.MARKDOWN)
        case draw.State():
            return rr.StateChange(state=item.value)
        case draw.StateStyle():
            return rr.StateConfiguration(values=item.values, colors=item.colors)
        case draw.Scalar():
            return rr.Scalars(item.value)
        case draw.SeriesStyle():
            return rr.SeriesLines(colors=item.color, names=item.name)
        case draw.ZUp():
            return rr.ViewCoordinates.RIGHT_HAND_Z_UP
    raise TypeError(f"nothing draws a {type(item).__name__}")


class RerunOutput:
    """One rerun recording of the fleet, written to `rrd` and/or streamed to a viewer:
    `viewer` is "spawn" (a native viewer on this machine), "web" (a web viewer served on WEB_PORT;
    the page to open is `web_address`) or the address of a running viewer (rerun+http://HOST:PORT/proxy)."""

    def __init__(self, rrd: str | None = None, viewer: str | None = None, recording_name: str = "falconry",
                 port: int = GRPC_PORT) -> None:
        if viewer is not None:
            check_viewer(viewer)
        # Chunks of up to a second: each chunk carries its own schema, so rerun's default 200 ms
        # made half of a recording's bytes overhead; a second of latency is nothing to a viewer.
        batching = rr.ChunkBatcherConfig(flush_tick=1.0, flush_num_bytes=4 << 20, flush_num_rows=10_000)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{recording_name}-{time.time_ns()}",
                                      batcher_config=batching)
        self.rec.set_log_time_enabled(False)
        self.rec.send_recording_name(recording_name)
        self.web_address: str | None = None
        sinks = []
        if rrd:
            sinks.append(rr.FileSink(rrd))
        if viewer == "spawn":
            spawn_viewer(port)
            sinks.append(rr.GrpcSink(grpc_address(port)))
        elif viewer == "web":
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=port)
            sinks.append(server)
            rr.serve_web_viewer(web_port=WEB_PORT, open_browser=False, connect_to=server.uri)
            self.web_address = web_address(port)
        elif viewer:
            sinks.append(rr.GrpcSink(viewer))
        self.rec.set_sinks(*sinks)
        self.logged = 0
        self._time: int | None = None  # the mission time the stream is set to
        self._uavs: list[str] | None = None  # the team the layout was sent for
        self.layout([])

    def layout(self, uavs: list[str]) -> None:
        """Send the layout for this team (again when a UAV appears)."""
        if uavs != self._uavs:
            self._uavs = list(uavs)
            self.rec.send_blueprint(blueprint(self._uavs), make_active=True, make_default=True)

    def write(self, logs: list[draw.Log]) -> None:
        rec = self.rec
        for log in logs:
            if log.stamp is not None and log.stamp != self._time:  # a message's logs share one time
                self._time = log.stamp
                rec.set_time("mission_time", duration=np.timedelta64(log.stamp, "ns"))
                if log.tick is not None:
                    rec.set_time("tick", sequence=log.tick)
            rec.log(log.entity, archetype(log.item), static=log.stamp is None)
            self.logged += 1

    def flush(self) -> None:
        self.rec.flush()

    def close(self, timeout: float = 10.0) -> str | None:
        """Finish every sink (the file's footer); returns why a viewer did not take everything, or None.
        A viewer that went away must not cost the file: the file sink is finished regardless."""
        problem = None
        try:
            self.rec.flush(timeout_sec=timeout)
        except Exception as exc:  # rerun reports a vanished viewer as a RuntimeError
            problem = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        finally:
            self.rec.disconnect()
        return problem


def spawn_viewer(port: int, wait_s: float = 10.0) -> None:
    """A native rerun viewer listening on `port`, unless one already does (it is used then).

    Started in a session of its own with no terminal attached: it outlives the run (the user is
    still looking at it) and never writes into a pipe that closed with the run. (rerun's own
    `spawn` leaves the viewer on the caller's output, which a supervisor stops reading.)"""
    if _listening(port):
        return
    subprocess.Popen([viewer_executable(), f"--port={port}", "--memory-limit=75%", "--expect-data-soon",
                      "--hide-welcome-screen"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                     stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + wait_s
    while not _listening(port):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the rerun viewer did not start listening on port {port} within {wait_s:g} s")
        time.sleep(0.1)


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
        return True
    except OSError:
        return False
