# detached: bash /var/tmp/after/.gpu-job/job.sh RUNS OUTNAME
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
WAIT_READY=900 bash benchmarks/gpu_runs60.sh /var/tmp/data /var/tmp/res/$2 /var/tmp/after/.gpu-job/$1 "$(cat .gpu-job/COMMIT)" > /var/tmp/res-$2.log 2>&1
