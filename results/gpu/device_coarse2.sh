# Second call on the same warm H200 (after device_coarse.sh): the width under today's default chosen on
# train images (64 and 256 particles beside the first call's 512), then 512 on 12 fsclvr test images.
export PYTHONUNBUFFERED=1
export PYTHONPATH=/tmp/site:$PWD
bench() { name=$1; limit=$2; shift 2
  echo "== $name"
  timeout $limit python3 scripts/bench_posterior.py .devdata/model "$@" --renderer jax > $OUT/$name.json 2> /tmp/$name.err
  echo "rc $?"; grep '^{"' $OUT/$name.json; grep -v Warning /tmp/$name.err | tail -3
}
bench train64_256_default 230 .devdata/train/[0-9][0-9].png --particles 64,256 --seeds 2 --truth .devdata/train/truth.json
bench test512_default 90 .devdata/images/[0-9][0-9].png --particles 512 --truth .devdata/images/truth.json
