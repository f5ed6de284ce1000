// Test-only: two cameras from Chromium's one file-backed fake camera.
//
// With --use-file-for-fake-video-capture Chromium offers exactly one camera, whatever
// device-count says (media/capture/video/create_video_capture_device_factory.cc). The
// file holds the simulated left and right views side by side; this script, injected
// before the page's own scripts, lists two cameras and gives each the frames of its half,
// cropped by the browser's insertable streams (MediaStreamTrackProcessor/Generator), so
// every frame keeps its capture timestamp. Everything else is the page's own code.
(() => {
  const md = navigator.mediaDevices;
  if (!md || typeof MediaStreamTrackProcessor === "undefined") return;
  const realGetUserMedia = md.getUserMedia.bind(md);
  const realEnumerate = md.enumerateDevices.bind(md);
  const HALVES = [
    { deviceId: "simulated-left-half", label: "Simulated camera (left half of the file)", index: 0 },
    { deviceId: "simulated-right-half", label: "Simulated camera (right half of the file)", index: 1 },
  ];
  md.enumerateDevices = async () => {
    const real = await realEnumerate();
    const others = real.filter((d) => d.kind !== "videoinput");
    return others.concat(HALVES.map((h) => ({
      deviceId: h.deviceId, groupId: h.deviceId, kind: "videoinput", label: h.label,
      toJSON() { return { deviceId: h.deviceId, groupId: h.deviceId, kind: "videoinput", label: h.label }; },
    })));
  };
  md.getUserMedia = async (constraints) => {
    const video = constraints && constraints.video;
    const wanted = video && video.deviceId && (video.deviceId.exact || video.deviceId.ideal || video.deviceId);
    const half = HALVES.find((h) => h.deviceId === wanted);
    if (!half) return realGetUserMedia(constraints);
    const source = await realGetUserMedia({ video: true });
    const track = source.getVideoTracks()[0];
    const processor = new MediaStreamTrackProcessor({ track });
    const generator = new MediaStreamTrackGenerator({ kind: "video" });
    // A read-crop-write loop rather than pipeThrough: a stream's queue drops the frames it
    // holds when the track stops, and a VideoFrame dropped without close() makes Chromium
    // warn ("garbage collected without being closed"). Here every frame is closed by
    // whoever holds it last: this loop, the generator once it has taken it, or stop().
    const reader = processor.readable.getReader();
    const writer = generator.writable.getWriter();
    const inflight = new Set(); // written, not yet taken by the generator
    let stopped = false;
    (async () => {
      while (!stopped) {
        const { value: frame, done } = await reader.read().catch(() => ({ done: true }));
        if (done) break;
        if (stopped) { frame.close(); break; }
        const width = frame.codedWidth / 2;
        const rect = { x: half.index * width, y: 0, width, height: frame.codedHeight };
        const cropped = new VideoFrame(frame, { visibleRect: rect });
        frame.close();
        inflight.add(cropped);
        try {
          await writer.write(cropped);
        } catch (error) {
          cropped.close(); // the generator stopped before taking it
          break;
        } finally {
          inflight.delete(cropped);
        }
      }
      reader.cancel().catch(() => {});
    })();
    const stop = generator.stop.bind(generator);
    // On stop, a frame may wait in the writable's queue (its write never settles once the
    // track has ended) and others in the processor's: close the one, cancel the other.
    generator.stop = () => {
      stopped = true;
      inflight.forEach((frame) => frame.close());
      inflight.clear();
      reader.cancel().catch(() => {});
      stop();
      track.stop();
    };
    return new MediaStream([generator]);
  };
})();
