# started on the warm machine while runs_l.txt ran: the mask A/B once the list is done
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
export PYTHONPATH=/var/tmp/after:${PYTHONPATH:-}
while [ ! -e /var/tmp/res/l/all.done ]; do sleep 2; done
mkdir -p /var/tmp/res/m2
DEVICE=cuda WARMUP=1000 python .gpu-job/mask_ab.py /var/tmp/data/blocks /var/tmp/res/m2/ab 2 > /var/tmp/res/m2/mask_ab.log 2>&1
touch /var/tmp/res/m2/all.done
