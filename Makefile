# Thin wrappers: the scripts are the source of truth (README's two commands).
.PHONY: extension demo test wheels clean

wheels:
	bash scripts/build_wheels.sh

extension:
	bash scripts/env.sh

demo:
	bash scripts/demo.sh

test:
	bash scripts/test.sh

clean:
	rm -rf dist out
