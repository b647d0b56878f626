# detached step-time A/B: bash .gpu-job/st.sh (copies the tree to /var/tmp/st first)
set -e
mkdir -p /var/tmp/st /var/tmp/res/st
tar cf - --exclude='./.gpu-warp*' --exclude='./.gpu-data' --exclude=./benchmarks/results . | (cd /var/tmp/st && tar xf -)
cat > /var/tmp/st/run.sh <<'SH'
cd /var/tmp/st && source /var/tmp/gpu-warp/activate.sh
export PYTHONPATH=$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1
[ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels
[ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
python3 .gpu-job/st_ab.py /var/tmp/data /var/tmp/res/st blocks plant shiny lattice toyset > /var/tmp/res/st.log 2>&1
echo "exit $?" >> /var/tmp/res/st.log
cp /var/tmp/res/st.log /var/tmp/res/st/ ; touch /var/tmp/res/st/all.done
SH
setsid nohup bash /var/tmp/st/run.sh > /dev/null 2>&1 < /dev/null &
sleep 2; ls /var/tmp/data; nvidia-smi --query-gpu=name --format=csv,noheader
