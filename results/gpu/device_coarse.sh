# The coarse wide start (today's default SMC) on a lent GPU, the JAX tracer end to end (no Mitsuba):
# 1. seconds per P3 posterior at the CPU's 64 particles, the default beside the sampler before the coarse
#    start (smc-narrow), 6 fsclvr test images, the last one profiled;
# 2. the GPU's 512 particles under today's default, 20 fsclvr *train* images x 2 seeds (the same images
#    and settings as bench_width_h200_train.json, which ran the narrow start).
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -c "import jax; print('jax', jax.__version__, jax.devices())" 2>&1 | tail -1
narrow="--set smc.wide=1 --set smc.wide_steps=0 --set smc.coarse=1"
bench() { name=$1; limit=$2; shift 2
  echo "== $name"
  timeout $limit python3 scripts/bench_posterior.py .devdata/model "$@" --renderer jax > $OUT/$name.json 2> /tmp/$name.err
  echo "rc $?"; grep '^{"' $OUT/$name.json; grep -v Warning /tmp/$name.err | tail -3
}
bench test64_default 150 .devdata/images/0[0-5].png --particles 64 --truth .devdata/images/truth.json --profile $OUT/profile_default.txt
bench test64_narrow 100 .devdata/images/0[0-5].png --particles 64 --truth .devdata/images/truth.json --profile $OUT/profile_narrow.txt $narrow
bench train512_default 300 .devdata/train/[0-9][0-9].png --particles 512 --seeds 2 --truth .devdata/train/truth.json
