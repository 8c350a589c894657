; Seed 000, Cincinnati Arrow 500 X axis (0..500 mm travel): point-to-point and linear
; moves like the paper's validation runs, each ending in an exact stop.
N10 G90 G71                ; absolute, metric
N20 G0 X250                ; rapid to mid travel, where the paper puts the nut
N30 G4 F0.5                ; dwell 0.5 s
N40 G1 X250.5 F200         ; 0.5 mm position step at 200 mm/min
N50 G4 F0.5
N60 G1 X300 F500           ; 49.5 mm at 500 mm/min
N70 G91 X-50               ; incremental: 50 mm back, still G1 F500
N80 G90 G0 X20             ; rapid towards the start of travel
N90 G4 F0.2
N100 G1 X480 F6000         ; long move at 6 m/min
N110 M30
