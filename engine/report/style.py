"""The look of forestreg's HTML reports: one style sheet for every report."""

#: The style of every forestreg HTML report (a report may add a few rules of its own).
REPORT_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, Arial, sans-serif; margin: 1.5em auto;
       max-width: 1250px; padding: 0 1em; color: #222; line-height: 1.4; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { font-size: 1.25em; border-bottom: 2px solid #ccd; padding-bottom: 0.15em; margin-top: 1.8em; }
h3 { font-size: 1.05em; margin-bottom: 0.3em; }
.sub { color: #555; margin-top: 0; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #c8c8d0; padding: 0.25em 0.55em; vertical-align: top; }
th { background: #eef0f7; text-align: left; font-weight: 600; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.failed td { background: #fff3f2; }
.ok { color: #1a7f37; font-weight: 600; }
.bad { color: #b42318; font-weight: 600; }
.failbox { background: #fdecea; border-left: 6px solid #b42318; padding: 0.6em 1em; margin: 1em 0; }
.failbox h3 { margin-top: 0.1em; color: #b42318; }
.okbox { background: #ecf7ee; border-left: 6px solid #1a7f37; padding: 0.6em 1em; margin: 1em 0; }
.note { color: #555; font-size: 0.88em; }
.changed { font-weight: 700; color: #7a3e00; }
figure { margin: 0.6em 0 1.2em 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { color: #444; font-size: 0.9em; margin-top: 0.3em; max-width: 70em; }
code { background: #f3f3f6; padding: 0 0.2em; }
.swatch { display: inline-block; width: 0.9em; height: 0.9em; border: 1px solid #555; vertical-align: -0.1em;
          margin-right: 0.3em; }
"""
