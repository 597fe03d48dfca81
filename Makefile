# Thin wrappers: the scripts are the source of truth (README's two commands).
.PHONY: extension demo test wheels clean

wheels:
	bash scripts/build_wheels.sh

# Every platform's zip (cp311 + cp313 scipy wheels each) into dist/.
extension:
	bash scripts/env.sh runtime
	bash scripts/build_extension.sh

demo:
	bash scripts/demo.sh

test:
	bash scripts/test.sh

clean:
	rm -rf dist out
