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
    const crop = new TransformStream({
      transform(frame, controller) {
        const width = frame.codedWidth / 2;
        const rect = { x: half.index * width, y: 0, width, height: frame.codedHeight };
        controller.enqueue(new VideoFrame(frame, { visibleRect: rect }));
        frame.close();
      },
    });
    processor.readable.pipeThrough(crop).pipeTo(generator.writable).catch(() => {});
    const stop = generator.stop.bind(generator);
    generator.stop = () => { stop(); track.stop(); };
    return new MediaStream([generator]);
  };
})();
