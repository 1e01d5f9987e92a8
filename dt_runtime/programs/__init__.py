"""The programs: what a cell is told to do, corrected by the twin's one corrector. Point programs
(`program`: `dt correct`), path programs and their interpolation into timed set-points (`path`),
a path's set-point table corrected offline (`path_correct`: `dt correct --path`, the daemon's path
runs) and the servo lag of a streamed path (`lag`).
"""
