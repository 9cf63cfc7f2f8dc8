#!/usr/bin/env bash
# Put the NLTK data the noise-word dictionary needs into $NLTK_DATA (default <repo>/.nltk_data),
# from Debian packages (no download at run time):
#   corpora/wordnet/  <- /usr/share/wordnet (package wordnet-base; index.sense from
#                        wordnet-sense-index) + a `lexnames` file written here (see lexnames(5))
#   corpora/words/en  <- /usr/share/dict/web2 (package miscfiles)
# Files are COPIED (not linked). Idempotent: running it again changes nothing.
# Usage: scripts/setup_nltk_data.sh        (needs root for apt-get when the packages are missing)
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NLTK_DATA="${NLTK_DATA:-$repo/.nltk_data}"

need_pkgs=()
[ -f /usr/share/wordnet/data.noun ] || need_pkgs+=(wordnet-base)
[ -f /usr/share/wordnet/index.sense ] || need_pkgs+=(wordnet-sense-index)
[ -f /usr/share/dict/web2 ] || need_pkgs+=(miscfiles)
if [ ${#need_pkgs[@]} -gt 0 ]; then
  echo "installing ${need_pkgs[*]} (apt-get)"
  apt-get install -y "${need_pkgs[@]}" || { apt-get update && apt-get install -y "${need_pkgs[@]}"; }
fi

wn="$NLTK_DATA/corpora/wordnet"
mkdir -p "$wn" "$NLTK_DATA/corpora/words"
for f in /usr/share/wordnet/*; do
  [ -f "$f" ] || continue                      # skip sub-folders (bin, pixmaps, wnres)
  cmp -s "$f" "$wn/$(basename "$f")" 2>/dev/null || cp "$f" "$wn/"
done

# lexnames(5): number, lexicographer file name, syntactic category (1 n, 2 v, 3 a, 4 r).
lex="$wn/lexnames.tmp.$$"
i=0
while read -r name cat; do
  printf '%02d\t%s\t%s\n' "$i" "$name" "$cat"
  i=$((i + 1))
done > "$lex" <<'LEX'
adj.all 3
adj.pert 3
adv.all 4
noun.Tops 1
noun.act 1
noun.animal 1
noun.artifact 1
noun.attribute 1
noun.body 1
noun.cognition 1
noun.communication 1
noun.event 1
noun.feeling 1
noun.food 1
noun.group 1
noun.location 1
noun.motive 1
noun.object 1
noun.person 1
noun.phenomenon 1
noun.plant 1
noun.possession 1
noun.process 1
noun.quantity 1
noun.relation 1
noun.shape 1
noun.state 1
noun.substance 1
noun.time 1
verb.body 2
verb.change 2
verb.cognition 2
verb.communication 2
verb.competition 2
verb.consumption 2
verb.contact 2
verb.creation 2
verb.emotion 2
verb.motion 2
verb.perception 2
verb.possession 2
verb.social 2
verb.stative 2
verb.weather 2
adj.ppl 3
LEX
if cmp -s "$lex" "$wn/lexnames"; then rm "$lex"; else mv "$lex" "$wn/lexnames"; fi

cmp -s /usr/share/dict/web2 "$NLTK_DATA/corpora/words/en" 2>/dev/null || cp /usr/share/dict/web2 "$NLTK_DATA/corpora/words/en"
echo "NLTK data ready in $NLTK_DATA (corpora/wordnet: $(ls "$wn" | wc -l) files, corpora/words/en: $(wc -l < "$NLTK_DATA/corpora/words/en") words)"
