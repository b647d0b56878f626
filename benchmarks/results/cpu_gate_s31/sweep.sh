# nineteenth session, 2-core CPU (Intel Xeon, AVX-512), tree 017e6fd; shiny173 = fastenerf synth --scene shiny --size 173x130 --frames 300; run st_g15 (2°) first, on its own: fastenerf bench study pose-error shiny173 --levels 2 --steps 3000 --device cpu --out st_g15 --set refine_poses=true smooth_poses=121 smooth_order=1
P="refine_poses=true smooth_poses=121 smooth_order=1"
run() { name=$1; levels=$2; shift 2; fastenerf bench study pose-error shiny173 --levels $levels --steps 3000 --device cpu --out st_$name --set "$@" > st_$name.log 2>&1; echo "$name done rc $?" >> sweep.log; }
run none "0 2" smooth_poses=0
run g15_0 "0" $P
run g0 "0 2" $P refine_gate=0
run g10 "0 2" $P refine_gate=1.0
run rs03 "2" $P refine_start=0.3
run lr1e2 "2" $P refine_lr=1e-2
echo all done >> sweep.log
