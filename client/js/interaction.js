// Camera input: drag to orbit, wheel or pinch to zoom, double-click to reset, and the keyboard
// (arrow keys orbit, + and - zoom, Home or R resets). All of it goes through the view state.

const DEG_PER_PIXEL = 0.35;
const KEY_STEP_DEG = 5;
const KEY_ZOOM = 1.1;

function isTextEntry(el) {
  if (!el) return false;
  if (el.isContentEditable) return true;
  const tag = el.tagName;
  if (tag === "TEXTAREA" || tag === "SELECT") return true;
  if (tag === "INPUT") return el.type !== "checkbox" && el.type !== "button" && el.type !== "radio";
  return false;
}

/**
 * @param {HTMLElement} surface   the element that receives drags and wheel events
 * @param {import("./state.js").ViewState} state
 * @param {{onInput?: (time:number) => void, onReset?: () => void}} hooks
 */
export function attachCameraInput(surface, state, { onInput = () => {}, onReset = () => {} } = {}) {
  const pointers = new Map(); // pointerId -> {x, y}
  let pinchDistance = null;

  const orbit = (dAz, dEl, time) => {
    onInput(time);
    state.orbit(dAz, dEl, { interactive: true, inputTime: time });
  };
  const zoom = (factor, time) => {
    onInput(time);
    state.zoom(factor, { interactive: true, inputTime: time });
  };
  const reset = () => {
    state.resetCamera();
    onReset();
  };

  surface.addEventListener("pointerdown", (event) => {
    if (event.button !== 0 && event.pointerType === "mouse") return;
    surface.setPointerCapture(event.pointerId);
    pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
    surface.classList.add("dragging");
    if (pointers.size === 2) pinchDistance = spread(pointers);
  });

  surface.addEventListener("pointermove", (event) => {
    const last = pointers.get(event.pointerId);
    if (!last) return;
    const dx = event.clientX - last.x;
    const dy = event.clientY - last.y;
    last.x = event.clientX;
    last.y = event.clientY;
    if (pointers.size === 1) {
      if (dx || dy) orbit(-dx * DEG_PER_PIXEL, dy * DEG_PER_PIXEL, event.timeStamp);
    } else if (pointers.size === 2 && pinchDistance) {
      const d = spread(pointers);
      if (d > 0) zoom(pinchDistance / d, event.timeStamp);
      pinchDistance = d;
    }
  });

  const release = (event) => {
    if (!pointers.delete(event.pointerId)) return;
    if (pointers.size < 2) pinchDistance = null;
    if (pointers.size === 0) surface.classList.remove("dragging");
  };
  surface.addEventListener("pointerup", release);
  surface.addEventListener("pointercancel", release);
  surface.addEventListener("lostpointercapture", release);

  surface.addEventListener(
    "wheel",
    (event) => {
      event.preventDefault();
      const pixels = event.deltaMode === 1 ? event.deltaY * 16 : event.deltaMode === 2 ? event.deltaY * 400 : event.deltaY;
      zoom(Math.exp(pixels * 0.0015), event.timeStamp);
    },
    { passive: false },
  );

  surface.addEventListener("dblclick", (event) => {
    event.preventDefault();
    reset();
  });

  // Keyboard: on the view itself, or anywhere on the page outside text entry and sliders.
  document.addEventListener("keydown", (event) => {
    if (event.altKey || event.ctrlKey || event.metaKey) return;
    const target = event.target;
    const onSurface = surface.contains(target);
    if (!onSurface && (isTextEntry(target) || (target && target.type === "range"))) return;
    const step = event.shiftKey ? 3 * KEY_STEP_DEG : KEY_STEP_DEG;
    const t = event.timeStamp;
    switch (event.key) {
      case "ArrowLeft":
        orbit(-step, 0, t);
        break;
      case "ArrowRight":
        orbit(step, 0, t);
        break;
      case "ArrowUp":
        orbit(0, step, t);
        break;
      case "ArrowDown":
        orbit(0, -step, t);
        break;
      case "+":
      case "=":
        zoom(1 / KEY_ZOOM, t);
        break;
      case "-":
      case "_":
        zoom(KEY_ZOOM, t);
        break;
      case "Home":
        reset();
        break;
      case "r":
      case "R":
        if (!onSurface && target && target.tagName === "BUTTON") return;
        reset();
        break;
      default:
        return;
    }
    event.preventDefault();
  });
}

function spread(pointers) {
  const [a, b] = [...pointers.values()];
  return Math.hypot(a.x - b.x, a.y - b.y);
}
