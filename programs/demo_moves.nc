; hil demo: a short program for the Arrow 500 X axis (about 1.3 s of motion): a rapid,
; a feed move back and a rapid home, each ending in an exact stop.
N10 G90 G71                ; absolute, metric
N20 G0 X50                 ; rapid 50 mm at 30 m/min
N30 G4 F0.1                ; dwell 0.1 s
N40 G1 X40 F3000           ; 10 mm back at 3 m/min
N50 G4 F0.1
N60 G0 X0                  ; rapid home
N70 M30
