// Typeset the formulas that pymdownx.arithmatex (generic mode) leaves in the pages: <span class="arithmatex">
// holds \( ... \) (inline), <div class="arithmatex"> holds \[ ... \] (display). KaTeX is served with the
// site (assets/katex/), so nothing is fetched from outside.
(function () {
  function typeset(root) {
    root.querySelectorAll(".arithmatex").forEach(function (el) {
      var tex = el.textContent.trim();
      var display = el.tagName === "DIV";
      if (/^\\[(\[]/.test(tex)) tex = tex.slice(2, -2);
      katex.render(tex, el, { displayMode: display, throwOnError: false });
    });
  }
  if (typeof document$ !== "undefined") {
    document$.subscribe(function () { typeset(document); });  // Material's page-load stream
  } else {
    document.addEventListener("DOMContentLoaded", function () { typeset(document); });
  }
})();
