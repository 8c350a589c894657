; A short program for the Arrow 500 XY machine (configs/machines/arrow500_xy.toml), about
; 1.2 s of motion: a rapid on the diagonal, a feed move on a slanted line, a rapid home;
; every block moves both axes on one straight line and ends in an exact stop.
N10 G90 G71                ; absolute, metric
N20 G0 X40 Y20             ; rapid on the line to (40, 20) mm
N30 G4 F0.1                ; dwell 0.1 s
N40 G1 X30 Y0 F3000        ; 3 m/min along the path, X and Y together
N50 G4 F0.1
N60 G0 X0 Y0               ; rapid home
N70 M30
