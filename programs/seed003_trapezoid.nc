; Seed 003 section 5, TLM test rig (600 mm travel): a trapezoidal velocity at 6000 mm/min,
; long enough for about 4 s at constant velocity in each direction.
N10 G90 G71
N20 G0 X50                 ; rapid to the start
N30 G4 F0.5
N40 G1 X450 F6000          ; 400 mm at 6000 mm/min: accelerate, constant rate, decelerate
N50 G4 F0.5
N60 G1 X50                 ; and back
N70 M30
