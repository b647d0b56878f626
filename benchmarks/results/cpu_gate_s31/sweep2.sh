# nineteenth session, second CPU sweep (tree 017e6fd; plant173/lattice173 made as shiny173); then lattice_ease at the tree with refine_gate_prior_deg: fastenerf bench study pose-error lattice173 --levels 0 2 --steps 3000 --device cpu --set refine_poses=true smooth_poses=121 smooth_order=1 refine_gate_prior_deg=0.05
P="refine_poses=true smooth_poses=121 smooth_order=1"
run() { scene=$1; name=$2; levels=$3; shift 3; fastenerf bench study pose-error ${scene}173 --levels $levels --steps 3000 --device cpu --out s2_${scene}_$name --set "$@" > s2_${scene}_$name.log 2>&1; echo "$scene $name done rc $?" >> sweep2.log; }
run shiny g15s1 "2" $P seed=1
run shiny g0s1 "2" $P refine_gate=0 seed=1
run lattice g15 "0 2" $P
run lattice g0 "0 2" $P refine_gate=0
run plant g15 "0 2" $P
run plant g0 "0 2" $P refine_gate=0
echo all done >> sweep2.log
