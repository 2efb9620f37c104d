// Parse PromQL expressions with Prometheus' own grammar (@prometheus-io/lezer-promql, the one
// Prometheus' web UI uses). Reads {"name": "expr", ...} on stdin; writes {"name": [errors]}:
// each error the offset of a syntax error and the text around it ([] when the expression parses).
import { parser } from "@prometheus-io/lezer-promql";

let input = "";
process.stdin.on("data", (chunk) => (input += chunk));
process.stdin.on("end", () => {
  const out = {};
  for (const [name, expr] of Object.entries(JSON.parse(input))) {
    const errors = [];
    parser.parse(expr).iterate({
      enter: (node) => {
        if (node.type.isError) {
          errors.push(`${node.from}: ${JSON.stringify(expr.slice(Math.max(0, node.from - 12), node.to + 12))}`);
        }
      },
    });
    out[name] = errors;
  }
  process.stdout.write(JSON.stringify(out) + "\n");
});
