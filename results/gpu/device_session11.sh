# One call on a lent GPU (eleventh session), the JAX tracer end to end (no Mitsuba wheel carried):
# 1. the project's JAX tracer beside the authors' tamayo tracer in one run (scripts/bench_tracers.py;
#    tamayo carried as .authors/, MIT, commit 99a4386 of oarriaga/bayesian-inverse-graphics);
# 2. seconds per P3 posterior under today's default SMC (the chart walk and the rendered symmetry move
#    since the last GPU figures) at the CPU's 64 particles, 12 fsclvr test images, the last profiled;
# 3. the GPU's 512 particles under today's default, 20 fsclvr train images x 2 seeds.
# Data: python results/gpu/prepare_devdata.py data/fsclvr-lo data/models/fsclvr-lo (.devdata, carried).
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee $OUT/gpu.txt
echo "== tracers"
timeout 110 python3 scripts/bench_tracers.py --authors .authors --batches 20,256,4096 --repeats 20 \
  --figure $OUT/tracers.png > $OUT/tracers.json 2> /tmp/tracers.err; echo "rc $?"
grep '^{"' $OUT/tracers.json; grep -v Warning /tmp/tracers.err | tail -3
bench() { name=$1; limit=$2; shift 2
  echo "== $name"
  timeout $limit python3 scripts/bench_posterior.py .devdata/model "$@" --renderer jax > $OUT/$name.json 2> /tmp/$name.err
  echo "rc $?"; grep '^{"' $OUT/$name.json; grep -v Warning /tmp/$name.err | tail -3
}
bench test64 170 .devdata/images/[0-9][0-9].png --particles 64 --truth .devdata/images/truth.json --profile $OUT/profile64.txt
bench train512 230 .devdata/train/[0-9][0-9].png --particles 512 --seeds 2 --truth .devdata/train/truth.json
