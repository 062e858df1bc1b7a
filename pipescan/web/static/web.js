// The network map: the wheel zooms, a drag moves, a double-click shows the whole network again.
// It only changes the SVG's viewBox; pages work without it. Nothing is loaded from elsewhere.
(function () {
  "use strict";
  for (const svg of document.querySelectorAll("svg.network-map")) {
    const home = svg.getAttribute("viewBox");
    const whole = svg.viewBox.baseVal.width;
    let drag = null;
    let moved = false;
    const at = (evt) => new DOMPoint(evt.clientX, evt.clientY).matrixTransform(svg.getScreenCTM().inverse());
    const show = (x, y, w, h) => svg.setAttribute("viewBox", [x, y, w, h].join(" "));
    svg.addEventListener("wheel", (evt) => {
      evt.preventDefault();
      const box = svg.viewBox.baseVal;
      const factor = evt.deltaY < 0 ? 0.8 : 1.25;
      const scale = Math.min(factor, whole / box.width);
      const p = at(evt);
      show(p.x - (p.x - box.x) * scale, p.y - (p.y - box.y) * scale, box.width * scale, box.height * scale);
    }, { passive: false });
    svg.addEventListener("pointerdown", (evt) => {
      if (evt.pointerType !== "mouse") return;  // touch scrolls the page
      drag = { p: at(evt), x: evt.clientX, y: evt.clientY };
      moved = false;
    });
    window.addEventListener("pointermove", (evt) => {
      if (!drag) return;
      if (Math.abs(evt.clientX - drag.x) + Math.abs(evt.clientY - drag.y) > 4) moved = true;
      if (!moved) return;
      const box = svg.viewBox.baseVal;
      const p = at(evt);
      show(box.x - (p.x - drag.p.x), box.y - (p.y - drag.p.y), box.width, box.height);
    });
    window.addEventListener("pointerup", () => { drag = null; });
    svg.addEventListener("click", (evt) => {
      if (moved) { evt.preventDefault(); evt.stopPropagation(); moved = false; }
    }, true);
    svg.addEventListener("dblclick", () => svg.setAttribute("viewBox", home));
  }
})();
