"""The stylesheet of rtsgt's HTML pages (the run's report, the batch summary, the plan), in one
place; importing it loads nothing else."""

#: The pages' CSS: screen and print (A4), tables, figures, verdict colours.
CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;color:#222;
background:#fafafa;line-height:1.45}
main{max-width:1180px;margin:0 auto;padding:1.2em 2em 3em}
h1{font-size:1.6em;margin:.2em 0}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;
margin-top:2em}h3{margin-top:1.4em}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em;background:#fff}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right;vertical-align:top}
th{background:#eef2f6}td.k,th.k{text-align:left;font-family:ui-monospace,monospace}
td.s{text-align:left}tr.all td{font-weight:bold}
.paper{color:#666;font-style:italic}
figure{margin:1.2em 0;background:#fff;border:1px solid #ddd;padding:.6em}
figure img{max-width:100%;height:auto;display:block;margin:0 auto}
figcaption{font-size:.9em;color:#444;margin-top:.4em}
.note{background:#fff8e1;border-left:4px solid #f0b400;padding:.5em .8em}
.kpi{display:flex;flex-wrap:wrap;gap:.8em}.kpi div{background:#fff;border:1px solid #ddd;
padding:.5em .9em;min-width:10em}.kpi b{display:block;font-size:1.3em}
nav a{margin-right:1em}details{margin:.4em 0}summary{cursor:pointer}
#rtsgt-view3d{height:720px;background:#fff;border:1px solid #ddd}
table{max-width:100%}td.s{overflow-wrap:break-word}code{overflow-wrap:anywhere}
tr.group th{background:#f6f6f6;text-align:left;font-family:inherit}
table.kv th.k{background:#f6f8fa;font-weight:normal;font-family:inherit}
table.kv th.k small{font-family:ui-monospace,monospace;color:#555}
#run-warnings{font-size:.85em}#run-warnings li{margin:.2em 0}.print-only{display:none}
@page{size:A4;margin:12mm 11mm}
@media print{
body{background:#fff;font-size:9.5pt;line-height:1.3}
main{max-width:none;padding:0}
nav{display:none}
h2{margin-top:1.2em;break-after:avoid}h3{break-after:avoid}
table{font-size:8pt}th,td{padding:.15em .35em}tr{break-inside:avoid}
figure{break-inside:avoid;border:none;padding:0}figure img{max-height:118mm;width:auto}
.kpi div{min-width:8em;padding:.3em .6em}
#rtsgt-view3d,#view .screen-only{display:none}.print-only{display:block}
}
"""
