; Identification test program: moves in both directions at several feeds (the friction
; map), slow moves (cogging and pitch error resolvable below the filter corner), and
; small reversals of 20 micrometres (presliding, backlash).
N10 G90 G71
N20 G1 X50 F4000
N30 G4 F0.05
N40 G1 X0 F4000
N50 G4 F0.05
N60 G1 X60 F2000
N70 G4 F0.05
N80 G1 X30 F1200
N90 G4 F0.05
N100 G1 X30.02 F60
N110 G1 X30 F60
N120 G1 X30.02 F60
N130 G1 X30 F60
N140 G1 X40 F800
N150 G4 F0.05
N160 G1 X0 F6000
N170 M30
