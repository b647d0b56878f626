# nineteenth session, third CPU sweep (tree 1f4210a+; blocks173 as the others, toyset173 = fastenerf synth --mesh toyset.ply --size 173x130 --frames 300, toyset.ply from fastenerf bench toyset)
P="refine_poses=true smooth_poses=121 smooth_order=1"
run() { scene=$1; name=$2; levels=$3; shift 3; fastenerf bench study pose-error ${scene}173 --levels $levels --steps 3000 --device cpu --out s4_${scene}_$name --set "$@" > s4_${scene}_$name.log 2>&1; echo "$scene $name done rc $?" >> sweep3.log; }
run blocks g15 "2" $P
run blocks g0 "2" $P refine_gate=0
run toyset g15 "2" $P
run toyset g0 "2" $P refine_gate=0
run shiny g15 "1" $P
run shiny g0 "1" $P refine_gate=0
run lattice g15 "1" $P
run lattice g0 "1" $P refine_gate=0
run plant g15 "1" $P
run plant g0 "1" $P refine_gate=0
echo all done >> sweep3.log
