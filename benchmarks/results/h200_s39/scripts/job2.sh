# the lattice runs cut from runs_l.txt, started on the warm machine after the list and the mask A/B:
# bash /var/tmp/after/.gpu-job/job2.sh (wrote /var/tmp/res/l2)
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
WAIT_READY=900 bash benchmarks/gpu_runs60.sh /var/tmp/data /var/tmp/res/l2 /var/tmp/after/.gpu-job/l2.txt "$(cat .gpu-job/COMMIT)" > /var/tmp/res-l2.log 2>&1
