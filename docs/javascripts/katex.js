// Math in the pages (pymdownx.arithmatex wraps it in .arithmatex elements). Notebook pages
// typeset their own math with the MathJax that mkdocs-jupyter includes.
document$.subscribe(({ body }) => {
  for (const element of body.querySelectorAll(".arithmatex")) {
    renderMathInElement(element, {
      delimiters: [
        { left: "\\[", right: "\\]", display: true },
        { left: "\\(", right: "\\)", display: false },
      ],
      throwOnError: false,
    });
  }
});
