; A short program for the GEISS five-axis machine (configs/machines/geiss_5axis.toml),
; about 1 s of motion: the linear axes on a line, then all five axes on one line (B and C
; follow the linear path in the same time), a rotary-only move, a rapid home.
N10 G90 G71                ; absolute, metric
N20 G0 X10 Y5 Z4           ; rapid, X Y Z on one line
N30 G1 X20 Y0 Z0 B5 C30 F3000   ; 3 m/min along the linear path; B and C with them
N40 G1 C60 F9000           ; rotary only: 9000 deg/min
N50 G4 F0.05               ; dwell 0.05 s
N60 G0 X0 Y0 Z0 B0 C0      ; rapid home, all five
N70 M30
