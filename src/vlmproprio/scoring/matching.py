"""A caption in a lexicon's terms: tokens, clauses, matched terms with one meaning each, and negation.

* A caption is tokenised (words, numbers, punctuation) and split into clauses at
  punctuation and at connectives such as "then" / "before" / "while".
* Lexicon terms (word sequences, longest match first, never overlapping) are
  matched; articles and possessives may sit between a term's words.
* A negation cue ("not", "without", "doesn't", ...) negates an action, direction
  or compartment term that follows within a few words in the same clause. Objects are never negated.
* Some verbs take their meaning from what follows (door.json ``contextual``): "push the lever down" turns
  the handle, "push the door" is the opposite of the pull that opens it. Phrasal verbs may be split
  (``gapped``: "set it down", "transfers the box from A to B"). A failure cue ("... but fails") negates
  the action before it.
* Row and side words ("far", "left") are compartment words only near a bin noun
  or as a row+side pair ("far left").

Nothing here depends on an episode: the same text and lexicon give the same :class:`TextAnalysis`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from vlmproprio.scoring.lexicon import _TOKEN_RE, Lexicon, Tag, Term


@dataclass(frozen=True)
class Token:
    text: str  # lower case
    start: int
    end: int
    clause: int
    is_word: bool


def tokenize(text: str, lexicon: Lexicon) -> list[Token]:
    out = []
    clause = 0
    matches = list(_TOKEN_RE.finditer(text))
    words = [m.group(0).lower().replace("’", "'") for m in matches]
    for i, m in enumerate(matches):
        tok = words[i]
        is_word = tok not in lexicon.clause_punct
        kept = i + 1 < len(words) and (tok, words[i + 1]) in lexicon.keep_together
        if not is_word or (tok in lexicon.clause_words and not kept):
            clause += 1
        out.append(Token(tok, m.start(), m.end(), clause, is_word))
    return out


@dataclass
class _Cand:
    first: int  # token index of the first and last matched token
    last: int
    term: Term
    kind: str = ""
    value: str = ""
    entry: str = ""
    negated: bool = False


def _match_terms(tokens: list[Token], lex: Lexicon) -> list[_Cand]:
    cands = []
    i = 0
    n = len(tokens)
    while i < n:
        tok = tokens[i]
        if not tok.is_word:
            i += 1
            continue
        found = None
        for term in lex.index.get(tok.text, ()):
            j, k = i + 1, 1
            while k < len(term.tokens) and j < n and tokens[j].is_word and tokens[j].clause == tok.clause:
                if tokens[j].text == term.tokens[k]:
                    k += 1
                elif tokens[j].text not in lex.skippable:
                    break
                j += 1
            if k == len(term.tokens):
                found = _Cand(i, j - 1, term)
                break
        if found is None:
            i += 1
        else:
            cands.append(found)
            i = found.last + 1
    return cands + _match_gapped(tokens, lex, cands)


def _match_gapped(tokens: list[Token], lex: Lexicon, cands: list[_Cand]) -> list[_Cand]:
    """Split phrasal verbs ("set it down"): extra candidates spanning verb..particle; words between keep theirs."""
    spans = {(c.first, c.last) for c in cands}
    objects = {c.first for c in cands if _tag(c, ("object",))}
    owned: dict[int, set[tuple[str, str]]] = {}  # the tags of the matches starting at each token
    for c in cands:
        owned.setdefault(c.first, set()).update((t.kind, t.value) for t in c.term.tags)
    out = []
    for i, tok in enumerate(tokens):
        gapped = lex.gapped.get(tok.text, ()) if tok.is_word else ()
        own = owned.get(i, set()) if gapped else set()
        for second, tag in gapped:
            for j in range(i + 1, min(len(tokens), i + lex.gapped_window + 2)):
                if not tokens[j].is_word or tokens[j].clause != tok.clause:
                    break
                if tokens[j].text == second:
                    needs = lex.gapped_needs.get(tag.value)
                    between = set(range(i + 1, j))
                    has_needed = needs is None or any(
                        tokens[k].text in needs or ("<object>" in needs and k in objects) for k in between
                    )
                    # skip when the unsplit phrase already matched, or the verb alone means the same
                    if (i, j) not in spans and (tag.kind, tag.value) not in own and has_needed:
                        term = Term((tok.text, second), (tag,))
                        out.append(_Cand(i, j, term, tag.kind, tag.value, tag.entry))
                    break
            else:
                continue
            break
    return out


def _tag(cand: _Cand, kinds: Sequence[str]) -> Tag | None:
    for t in cand.term.tags:
        if t.kind in kinds:
            return t
    return None


def _resolve(cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> list[_Cand]:
    """Give each match one meaning; compartment words need a bin noun nearby or a row+side pair."""
    nouns = [c for c in cands if _tag(c, ("noun",))]
    window = lex.compartment.window if lex.compartment else 0

    def near_noun(c: _Cand) -> bool:
        return any(
            tokens[n.first].clause == tokens[c.first].clause
            and min(abs(n.first - c.last), abs(c.first - n.last)) <= window
            for n in nouns
        )

    def pair(c: _Cand, kind: str) -> bool:
        others = ("side",) if kind in ("row", "image_row") else ("row", "image_row")
        return any(o is not c and _tag(o, others) and (o.first == c.last + 1 or c.first == o.last + 1) for o in cands)

    for c in cands:
        if c.kind:  # split phrasal verbs come tagged
            continue
        column = _tag(c, ("column",)) if lex.compartment else None
        comp = _tag(c, ("row", "image_row", "side")) if lex.compartment else None
        if column is not None:
            chosen = column
        elif comp is not None and (near_noun(c) or pair(c, comp.kind)):
            chosen = comp
        else:
            order = (
                "neutral",
                "negation",
                "failure",
                "source",
                "noun",
                "object",
                "wrong_action",
                "contextual",
                "action",
                "direction",
            )
            chosen = next((t for k in order for t in c.term.tags if t.kind == k), None)
        if chosen is not None:
            c.kind, c.value, c.entry = chosen.kind, chosen.value, chosen.entry
    out = sorted((c for c in cands if c.kind), key=lambda c: (c.first, c.last))
    _resolve_contextual(out, tokens, lex)
    return out


def _resolve_contextual(cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> None:
    """'push the lever down' turns the handle; 'push the door' is a wrong action (door.json action.contextual)."""
    for c in cands:
        if c.kind != "contextual":
            continue
        rule = lex.contextual[c.value]
        clause = tokens[c.first].clause
        nxt = next(
            (
                o
                for o in cands
                if o.first > c.last
                and o.kind in ("object", "direction", "noun")
                and tokens[o.first].clause == clause
                and o.first - c.last <= rule.window
            ),
            None,
        )
        said = " ".join(t.text for t in tokens[nxt.first : nxt.last + 1]) if nxt else ""
        if nxt is not None and (said in rule.when_next_is or said.split()[-1] in rule.when_next_is):
            c.kind, c.value = "action", rule.as_group
        else:
            c.kind, c.value = "wrong_action", rule.name
        c.entry = rule.entry


def _negated(c: _Cand, cands: list[_Cand], tokens: list[Token], lex: Lexicon) -> bool:
    clause = tokens[c.first].clause
    for j in range(max(0, c.first - lex.negation_window), c.first):
        if tokens[j].clause == clause and tokens[j].text.endswith(lex.negation_suffixes):
            return True
    return any(
        o.kind == "negation" and tokens[o.first].clause == clause and 0 < c.first - o.last <= lex.negation_window
        for o in cands
    )


@dataclass(frozen=True)
class TextAnalysis:
    """What a caption says in a lexicon's terms, before any episode judges it: its tokens, its matches (each
    with one meaning and whether it is negated) and the actions a failure cue takes back. The same text and
    lexicon give the same analysis; nothing downstream changes it, so cells with the same caption share it."""

    tokens: list[Token]
    cands: list[_Cand]
    failed: set[int]  # ids of the action candidates a later failure cue negates


def analyse_text(text: str, lexicon: Lexicon) -> TextAnalysis:
    """Tokenize ``text`` and match, resolve and negate its terms (the expectation-free half of ``score_text``)."""
    tokens = tokenize(text or "", lexicon)
    cands = _resolve(_match_terms(tokens, lexicon), tokens, lexicon)
    for c in cands:
        if c.kind in ("action", "wrong_action", "direction", "row", "image_row", "side", "column"):
            c.negated = _negated(c, cands, tokens, lexicon)
    return TextAnalysis(tokens, cands, _failed_actions(cands, tokens))


def _failed_actions(cands: list[_Cand], tokens: list[Token]) -> set[int]:
    """ids of the action candidates that a later failure cue ("... but fails") negates: the nearest action
    before each cue in the same sentence."""
    out = set()
    for f in cands:
        if f.kind != "failure":
            continue
        for c in sorted((c for c in cands if c.kind == "action" and c.last < f.first), key=lambda c: -c.last):
            if any(t.text in (".", "!", "?") for t in tokens[c.last : f.first]):
                break
            out.add(id(c))
            break
    return out
