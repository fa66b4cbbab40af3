# One call on a lent GPU (thirtieth session), the JAX tracer end to end (no Mitsuba carried: the
# JAX-tracer evaluation needs none):
# 1. `evaluate` of room's and dark's whole test splits (120 test + 90 spread posteriors each) with the JAX
#    tracer at 64 particles, both at once, 4 workers each sharing the GPU; the caches come back as .txz (split in 15 MB parts)
#    (they record .devdata paths, so they resume only there: a run folder refuses a data set in another folder;
#    device_evaluate.sh places the data at this machine's paths instead);
# 2. seconds per P3 posterior under today's default (shading fields, up to two rounds) at the CPU's 64
#    particles, 8 room test images (every 10th), one process, the last profiled.
# Data: python results/gpu/prepare_devdata.py data/room-lo data/models/room-white, and the two data sets
# and models copied to .devdata/{room,dark}-lo and .devdata/{room,dark}-model (carried).
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee $OUT/gpu.txt
nproc; python3 -c "import jax; print(jax.__version__, jax.devices())"
evaluate() { name=$1; limit=$2
  ( start=$(date +%s)
    timeout $limit python3 -m mitsuba_p3.cli evaluate .devdata/$name-lo --model .devdata/$name-model --out /tmp/eval-$name \
      --likelihoods p3 --renderer jax --particles 64 --jobs 4 > /tmp/eval-$name.log 2>&1
    echo "$name rc $? after $(( $(date +%s) - start )) s" >> /tmp/eval-$name.log
    tar cJf /tmp/eval-$name.txz -C /tmp eval-$name eval-$name.log && split -b 15M /tmp/eval-$name.txz $OUT/eval-$name.txz. ) &
}
echo "== evaluate room and dark"
evaluate room 360; evaluate dark 360; wait
tail -4 /tmp/eval-room.log /tmp/eval-dark.log; ls -la $OUT
echo "== posterior seconds (one process, after the evaluations: JAX's persistent cache holds their programs)"
XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 170 python3 scripts/bench_posterior.py .devdata/model .devdata/images/0[0-7].png \
  --renderer jax --particles 64 --truth .devdata/images/truth.json --profile $OUT/profile64.txt > $OUT/test64.json 2> /tmp/test64.err
echo "rc $?"; grep '^{"' $OUT/test64.json | cut -c1-1500; grep -v Warning /tmp/test64.err | tail -3
